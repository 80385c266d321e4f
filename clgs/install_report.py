"""What is installed beside clgs, and its size on disk: ``python -m clgs.install_report``.

Printed by the set-up so that a user sees what an install cost. Sizes are the files each
distribution's record lists (what ``pip uninstall`` would remove), so packages pulled in by others
count once each; editable installs count their metadata only.
"""
from __future__ import annotations

import contextlib
import importlib.metadata as md
import os
import sys


def distribution_sizes() -> dict:
    """{distribution name: bytes on disk} for every distribution on this interpreter's path."""
    sizes: dict = {}
    for dist in md.distributions():
        name = dist.metadata["Name"] or "?"
        total = 0
        for f in dist.files or ():
            with contextlib.suppress(OSError):
                total += os.path.getsize(dist.locate_file(f))
        sizes[name] = max(sizes.get(name, 0), total)
    return sizes


def main(top: int = 8) -> None:
    sizes = distribution_sizes()
    total = sum(sizes.values())
    big = sorted(sizes.items(), key=lambda kv: -kv[1])[:top]
    print(f"installed in {sys.prefix}: {len(sizes)} Python distributions, {total / 2**30:.2f} GiB")
    print("largest: " + ", ".join(f"{n} {b / 2**20:.0f} MB" for n, b in big))
    cuda = sorted(n for n in sizes if n.lower().startswith("nvidia-"))
    if cuda:
        print("CUDA libraries (from the compare extra's ASTRA, not needed by clgs): " + ", ".join(cuda))


if __name__ == "__main__":
    main()
