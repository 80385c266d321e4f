"""Where the ``.cl`` sources live and how one is built: the bottom of :mod:`clgs.runtime`, used
by the device probe (:mod:`.devices`) and the program cache (:mod:`.programs`) alike, so that
neither has to import the other's module to build a kernel."""
from __future__ import annotations

import warnings
from pathlib import Path

import pyopencl as cl


def cl_source_dir() -> Path:
    """Folder holding the ``.cl`` sources: inside an installed wheel, else the checkout's ``cl/``."""
    pkg = Path(__file__).resolve().parent.parent
    for candidate in (pkg / "cl", pkg.parent / "cl"):
        if (candidate / "common.h").is_file():
            return candidate
    raise FileNotFoundError(
        f"OpenCL sources not found next to {pkg} (looked in clgs/cl and ../cl); "
        "reinstall clgs with 'pip install .'"
    )


def build(ctx, source: str, options) -> cl.Program:
    """``source`` built for ``ctx`` with the project's headers on the include path. Drivers that
    print remarks on success (Intel's runtime does, for every program) stay quiet; set
    ``PYOPENCL_COMPILER_OUTPUT=1`` to see them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        return cl.Program(ctx, source).build(options=list(options) + ["-I", str(cl_source_dir())])
