"""Paths that data files name: a scan folder (or a model description) comes from elsewhere and is
data, never an instruction to read anything outside it."""
from __future__ import annotations

from pathlib import Path

from clgs.errors import ClgsError


class OutsideFolderError(ClgsError, ValueError):
    """A description names a file outside its own folder."""


def inside(folder, name, what: str, described_in: str) -> Path:
    """``folder / name``, refused unless it stays inside ``folder`` once resolved (no parent steps
    out, no absolute path, no link pointing out)."""
    folder = Path(folder)
    text = str(name)
    if not text or "\x00" in text:
        raise OutsideFolderError(f"{folder / described_in}: the {what} file name {name!r} is empty or invalid")
    path = folder / text
    try:
        resolved = path.resolve()
        root = folder.resolve()
    except (OSError, RuntimeError) as exc:  # link loops
        raise OutsideFolderError(f"{folder / described_in}: the {what} file {name!r} cannot be resolved "
                                 f"({exc})") from None
    if not (resolved == root or root in resolved.parents):
        raise OutsideFolderError(
            f"{folder / described_in}: the {what} file {name!r} lies outside the scan folder ({resolved}); a scan "
            "folder may name only files inside it: copy the file into the folder and name it there")
    return path
