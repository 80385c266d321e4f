"""OpenCL drivers: the environment they read, and Intel's CPU runtime from PyPI made visible.

Everything here must happen before the OpenCL ICD loader first runs (pyopencl's first
``get_platforms``): :func:`configure` runs once, when clgs first lists the devices (importing clgs
changes nothing in the process; call :func:`configure` yourself to have it earlier).

Two CPU drivers are supported and tested: PoCL (Debian's ``pocl-opencl-icd``, or
``pocl-binary-distribution`` from PyPI on CPUs its LLVM knows) and Intel's CPU runtime
(``intel-opencl-rt`` from PyPI, a dependency of clgs on x86-64 Linux). The wheel of Intel's runtime ships an
``.icd`` file that names a path which does not exist (``/opt/anaconda1anaconda2anaconda3/...``),
so the ICD loader never finds it. Here, when that package is installed and the user has not set
``OCL_ICD_VENDORS`` themselves, clgs writes a vendors folder in its cache that holds the
system's ``.icd`` files plus one naming the installed ``libintelocl.so`` by its real path, and
points ``OCL_ICD_VENDORS`` at it. The library finds its own dependencies through its RUNPATH.
"""
from __future__ import annotations

import hashlib
import os
import sys
import tempfile
from pathlib import Path

SYSTEM_VENDORS = Path("/etc/OpenCL/vendors")


def core_count() -> int:
    """Cores this process may run on (its affinity mask, not the machine's count)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def pocl_defaults() -> None:
    """PoCL's thread settings (read when its platform is first initialised): one thread per core
    with affinity is measurably faster and steadier; a user's own settings always win."""
    ncores = str(core_count())
    os.environ.setdefault("POCL_AFFINITY", "1")
    os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", ncores)
    os.environ.setdefault("POCL_CPU_MAX_CU_NUM", ncores)


def intel_cpu_library() -> Path | None:
    """``libintelocl.so`` of an installed ``intel-opencl-rt`` package, or None."""
    from importlib import metadata

    try:
        files = metadata.distribution("intel-opencl-rt").files or []
    except metadata.PackageNotFoundError:
        return None
    for f in files:
        if f.name == "libintelocl.so":
            path = Path(f.locate()).resolve()
            if path.is_file():
                return path
    return None


def _cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "clgs" / "opencl-vendors"


def _write_vendors(entries: dict[str, str]) -> Path:
    """A folder holding ``entries`` (file name -> library path) as ``.icd`` files. Its name is a
    hash of the contents, so processes started at once (a cluster's workers) agree on it, and
    each file is written by rename, so none is ever seen half-written."""
    text = "".join(f"{k}={v}\n" for k, v in sorted(entries.items()))
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    for root in (_cache_root(), Path(tempfile.gettempdir()) / f"clgs-opencl-vendors-{os.getuid()}"):
        folder = root / digest
        try:
            folder.mkdir(parents=True, exist_ok=True)
            for name, lib in entries.items():
                target = folder / name
                if target.is_file() and target.read_text().strip() == lib:
                    continue
                fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".part")
                with os.fdopen(fd, "w") as fh:
                    fh.write(lib + "\n")
                os.replace(tmp, target)
            return folder
        except OSError:
            continue
    raise OSError("no writable folder for the OpenCL vendor list")


def register_intel_cpu_runtime() -> Path | None:
    """Make Intel's CPU runtime from PyPI visible to the ICD loader (see the module's docstring).
    Returns the vendors folder used, or None when there is nothing to do (package absent, or the
    user chose the loader's folder with ``OCL_ICD_VENDORS``)."""
    if os.environ.get("OCL_ICD_VENDORS"):
        return None
    lib = intel_cpu_library()
    if lib is None:
        return None
    system = Path(os.environ.get("OPENCL_VENDOR_PATH") or SYSTEM_VENDORS)
    entries: dict[str, str] = {}
    if system.is_dir():
        for icd in sorted(system.glob("*.icd")):
            try:
                line = icd.read_text().strip()
            except OSError:
                continue
            if line and "intelocl" not in line:  # a broken system entry for the same runtime is replaced
                entries[icd.name] = line
    entries["clgs-intel-cpu.icd"] = str(lib)
    try:
        folder = _write_vendors(entries)
    except OSError as exc:  # a read-only home and /tmp: the system drivers still work
        print(f"clgs: could not register Intel's OpenCL runtime ({exc})", file=sys.stderr)
        return None
    os.environ["OCL_ICD_VENDORS"] = str(folder)
    return folder


_configured = [False]


def configure() -> None:
    """Everything the drivers read from the environment, once, before the ICD loader first runs:
    PoCL's thread settings, Intel's runtime made visible, and torch's idle OpenMP threads asked to
    sleep (they would spin on the cores PoCL's threads need; read when torch is first imported).
    A user's own settings always win."""
    if _configured[0]:
        return
    _configured[0] = True
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    pocl_defaults()
    register_intel_cpu_runtime()
