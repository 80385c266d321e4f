"""Atomic writes: a file or a folder appears complete under its final name, or not at all.

Files are written to a hidden temporary sibling in the same folder (same file system, so
``os.replace`` is an atomic rename) and flushed to disk first. The temporary name ends with the
target's own name, so libraries that pick a format from the suffix (nibabel's ``.nii.gz``,
trimesh's ``.stl``) behave as for the target. Folders are built in a temporary sibling folder and
renamed into place; replacing an existing folder renames the old one aside first, so the target
name always holds either the old or the new complete folder.
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import os
import shutil
import uuid
from pathlib import Path

from clgs.errors import ClgsError

__all__ = [
    "atomic_path", "atomic_dir", "write_bytes", "write_text", "write_json", "save_npy", "save_npz",
    "json_safe", "DiskFullError",
]


class DiskFullError(ClgsError, OSError):
    """The disk filled up while an output was being written; nothing was replaced."""


def _reraise(exc: OSError, target: Path):
    """Raise ``exc`` again, as a DiskFullError naming ``target`` when it is a full disk (or quota)."""
    import errno

    if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
        raise exc
    try:
        free = shutil.disk_usage(target.parent if target.parent.exists() else ".").free
        room = f"{free / 2**20:.0f} MiB left there"
    except OSError:
        room = "no room left"
    advice = "free some space and run again"
    checkpoint = target.parent / "checkpoint.pt"  # clgs.fit.config.CHECKPOINT: a run that can be resumed
    if checkpoint.is_file():
        advice = (f"the run's last checkpoint ({checkpoint}) is kept: free some space, then continue the run with "
                  "--resume (resume=True in Python)")
    raise DiskFullError(exc.errno, f"the disk is full while writing {target} ({room}); nothing was replaced "
                                   f"and no partial output was left: {advice}") from None


def _temp_sibling(path: Path) -> Path:
    return path.with_name(f".{uuid.uuid4().hex[:12]}.tmp.{path.name}")


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - not every platform can open folders
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path, overwrite: bool = True):
    """Yield a temporary path next to ``path``; on success it is renamed onto ``path``.

    On an exception the temporary file is removed and ``path`` is untouched. With
    ``overwrite=False`` an existing ``path`` raises FileExistsError before anything is written.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise FileExistsError(f"{path} already exists")
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; cannot write a file there")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_sibling(path)
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"nothing was written to the temporary file for {path}")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as exc:
        _reraise(exc, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes(path, data: bytes, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path, overwrite) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return Path(path)


def write_text(path, text: str, overwrite: bool = True) -> Path:
    return write_bytes(path, text.encode("utf-8"), overwrite)


def json_safe(obj):
    """A copy of ``obj`` that strict JSON can hold: NumPy scalars/arrays become Python numbers and
    lists, non-finite floats become None (JSON has no inf/NaN)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):  # NumPy array or scalar
        return json_safe(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path, obj, overwrite: bool = True, indent: int = 1) -> Path:
    """Write ``obj`` as strict JSON (see :func:`json_safe`), atomically."""
    text = json.dumps(json_safe(obj), indent=indent, allow_nan=False) + "\n"
    return write_text(path, text, overwrite)


def save_npy(path, array, overwrite: bool = True) -> Path:
    """``np.save`` atomically; the name is kept exactly (no ``.npy`` appended)."""
    import numpy as np

    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return write_bytes(path, buf.getvalue(), overwrite)


def save_npz(path, overwrite: bool = True, compressed: bool = False, **arrays) -> Path:
    """``np.savez`` (or ``savez_compressed``) atomically; arrays only, never pickled objects."""
    import numpy as np

    for name, value in arrays.items():
        if np.asarray(value).dtype == object:
            raise TypeError(f"array {name!r} has dtype object; npz files here hold numeric arrays only")
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return write_bytes(path, buf.getvalue(), overwrite)


@contextlib.contextmanager
def atomic_dir(path, overwrite: bool = False):
    """Yield a temporary sibling folder to fill; on success it becomes ``path``.

    ``overwrite=False`` refuses an existing ``path`` (FileExistsError) before any work. With
    ``overwrite=True`` an existing folder is renamed aside, the new one renamed in, then the old
    one deleted; an existing *file* at ``path`` is never replaced by a folder. On an exception the
    temporary folder is deleted and ``path`` is untouched.
    """
    path = Path(path)
    if path.exists():
        if not overwrite:
            raise FileExistsError(f"{path} already exists")
        if not path.is_dir():
            raise FileExistsError(f"{path} exists and is a file, not a folder")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_sibling(path)
    tmp.mkdir()
    try:
        yield tmp
        for p in tmp.rglob("*"):
            if p.is_file():
                with open(p, "rb+") as fh:
                    os.fsync(fh.fileno())
        old = None
        if path.exists():
            old = path.with_name(f".{uuid.uuid4().hex[:12]}.old.{path.name}")
            os.replace(path, old)
        try:
            os.replace(tmp, path)
        except BaseException:
            if old is not None:
                os.replace(old, path)
            raise
        _fsync_dir(path.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        _reraise(exc, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
