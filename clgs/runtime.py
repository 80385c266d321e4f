"""OpenCL runtime: device choice, PoCL settings, and a per-(context, options) program cache.

Every kernel wrapper in clgs gets its context, queue and compiled programs from here, so a
program is compiled once per process for each set of ``-D`` options and its kernel objects are
reused (PoCL recompiles on the first launch of each kernel, so re-creating them is costly).
"""
from __future__ import annotations

import os
import threading
from pathlib import Path

# PoCL reads these when the platform is first initialised, so set them before pyopencl loads.
# One thread per core with affinity is measurably faster and steadier on PoCL's CPU device;
# a user's own settings always win.
_NCORES = str(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))
os.environ.setdefault("POCL_AFFINITY", "1")
os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", _NCORES)
os.environ.setdefault("POCL_CPU_MAX_CU_NUM", _NCORES)
os.environ.setdefault("PYOPENCL_NO_CACHE", "1")  # PoCL keeps its own kernel cache

try:
    import pyopencl as cl
except ImportError as exc:  # pragma: no cover - exercised only without pyopencl
    raise ImportError(
        "clgs needs pyopencl and an OpenCL driver. Install them with\n"
        "    pip install 'pyopencl[pocl]'\n"
        "(PoCL's CPU driver from PyPI), or install your GPU vendor's OpenCL driver."
    ) from exc

_lock = threading.Lock()
_context: "cl.Context | None" = None
_queue: "cl.CommandQueue | None" = None
_programs: dict = {}


class NoOpenCLDevice(RuntimeError):
    """Raised when no OpenCL platform or device can be found."""


def cl_source_dir() -> Path:
    """Folder holding the ``.cl`` sources: inside an installed wheel, else the checkout's ``cl/``."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "cl", here.parent / "cl"):
        if (candidate / "common.h").is_file():
            return candidate
    raise FileNotFoundError(
        f"OpenCL sources not found next to {here} (looked in clgs/cl and ../cl); "
        "reinstall clgs with 'pip install .'"
    )


def _all_devices():
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise NoOpenCLDevice(
            "No OpenCL platform found. Install PoCL's CPU driver with "
            "\"pip install 'pyopencl[pocl]'\" or a GPU vendor's OpenCL driver "
            f"(pyopencl said: {exc})."
        ) from exc
    devices = []
    for p in platforms:
        try:
            devices.extend(p.get_devices())
        except cl.Error:
            continue
    if not devices:
        raise NoOpenCLDevice(
            "OpenCL platforms exist but expose no device. Install PoCL's CPU driver with "
            "\"pip install 'pyopencl[pocl]'\" or check your GPU driver."
        )
    return devices


def _pick_device():
    """Best device: a GPU (most compute units x clock), else the first CPU, else anything."""
    devices = _all_devices()
    gpus = [d for d in devices if d.type & cl.device_type.GPU]
    if gpus:
        return max(gpus, key=lambda d: d.max_compute_units * max(d.max_clock_frequency, 1))
    cpus = [d for d in devices if d.type & cl.device_type.CPU]
    return (cpus or devices)[0]


def get_context() -> "cl.Context":
    """The process-wide context; honours ``PYOPENCL_CTX`` when the user set it."""
    global _context
    with _lock:
        if _context is None:
            if os.environ.get("PYOPENCL_CTX"):
                try:
                    _context = cl.create_some_context(interactive=False)
                except cl.Error as exc:
                    raise NoOpenCLDevice(
                        f"PYOPENCL_CTX={os.environ['PYOPENCL_CTX']!r} names no usable device ({exc}); "
                        "unset it or run 'clgs info' to list devices."
                    ) from exc
            else:
                _context = cl.Context([_pick_device()])
        return _context


def get_queue() -> "cl.CommandQueue":
    """The process-wide in-order queue on the chosen device."""
    global _queue
    ctx = get_context()
    with _lock:
        if _queue is None:
            _queue = cl.CommandQueue(ctx)
        return _queue


def device() -> "cl.Device":
    return get_context().devices[0]


def is_cpu_device() -> bool:
    """True when device memory is host memory (buffers can wrap NumPy arrays without copies)."""
    return bool(device().type & cl.device_type.CPU)


def supports_double() -> bool:
    return "cl_khr_fp64" in device().extensions


_launch_lock = threading.Lock()
_kernel_args: dict = {}  # id(kernel) -> the arguments it was last launched with (kernels are cached)


def launch(queue, kernel, gsize, lsize, *args):
    """Enqueue ``kernel`` setting only the arguments that changed since its last launch (the same
    buffer object, or an equal scalar of the same type, is kept): pyopencl spends about 8-10 us per
    scalar argument, more than a small kernel runs, and most stay the same call after call. Kernels
    are cached per program and shared, hence one module-wide record. Returns the event."""
    import pyopencl as cl

    with _launch_lock:
        last = _kernel_args.get(id(kernel))
        if last is None or len(last) != len(args):
            last = _kernel_args[id(kernel)] = [None] * len(args)
        for i, v in enumerate(args):
            old = last[i]
            if old is v:
                continue
            if isinstance(v, cl.MemoryObjectHolder) or old is None or type(old) is not type(v) or old != v:
                kernel.set_arg(i, v)
            last[i] = v
        return cl.enqueue_nd_range_kernel(queue, kernel, gsize, lsize)


_shared: dict = {}
_shared_lock = threading.Lock()


def shared(cls):
    """The process-wide instance of ``cls`` (an operator class: its compiled programs and pooled
    buffers then serve every call), made on first use."""
    with _shared_lock:
        obj = _shared.get(cls)
        if obj is None:
            obj = _shared[cls] = cls()
        return obj


def round_up(n: int, m: int) -> int:
    """``n`` rounded up to a multiple of ``m`` (global sizes, padded rows)."""
    return (n + m - 1) // m * m


def real_name(dtype, what: str, error=ValueError) -> str:
    """The kernels' ``REAL`` for a NumPy float dtype; ``error`` (naming ``what``) for any other."""
    import numpy as np

    if dtype == np.float32:
        return "float"
    if dtype == np.float64:
        return "double"
    raise error(f"{what} must be float32 or float64, got {dtype}")


def _format_options(defines: dict | None) -> tuple:
    opts = []
    for key in sorted(defines or {}):
        value = defines[key]
        if value is True:
            opts.append(f"-D{key}")
        elif value is False or value is None:
            continue
        else:
            opts.append(f"-D{key}={value}")
    return tuple(opts)


class Program:
    """A compiled program plus its kernel objects, cached per (context, sources, options)."""

    def __init__(self, ctx, source: str, options: tuple):
        self.options = options
        self._program = cl.Program(ctx, source).build(options=list(options) + ["-I", str(cl_source_dir())])
        self._kernels: dict = {}

    def kernel(self, name: str) -> "cl.Kernel":
        k = self._kernels.get(name)
        if k is None:
            k = self._kernels[name] = getattr(self._program, name)
        return k


def get_program(filename: str, defines: dict | None = None, ctx=None) -> Program:
    """Compile ``cl/<filename>`` with ``-D`` options (``{"REAL": "double", "CONE": True}``), cached.

    ``REAL`` defaults to ``float``. The source may ``#include "common.h"``.
    """
    ctx = ctx or get_context()
    defines = dict(defines or {})
    defines.setdefault("REAL", "float")
    if defines["REAL"] == "double" and "cl_khr_fp64" not in ctx.devices[0].extensions:
        raise RuntimeError(f"device {ctx.devices[0].name!r} has no double precision (cl_khr_fp64)")
    if defines["REAL"] == "double":
        defines["REAL_DOUBLE"] = True
    options = _format_options(defines)
    key = (id(ctx), filename, options)
    with _lock:
        prog = _programs.get(key)
    if prog is None:
        path = cl_source_dir() / filename
        source = path.read_text()
        prog = Program(ctx, source, options)
        with _lock:
            _programs[key] = prog
    return prog


def describe() -> str:
    """Human-readable summary of platforms, devices, the chosen device and versions (``clgs info``)."""
    import numpy as np

    lines = [f"pyopencl {cl.VERSION_TEXT}, numpy {np.__version__}"]
    try:
        import torch

        lines.append(f"torch {torch.__version__}")
    except ImportError:
        lines.append("torch: not installed")
    try:
        chosen = device()
    except NoOpenCLDevice as exc:
        lines.append(str(exc))
        return "\n".join(lines)
    for p in cl.get_platforms():
        lines.append(f"platform: {p.name} ({p.version})")
        for d in p.get_devices():
            mark = "*" if d.int_ptr == chosen.int_ptr else " "
            fp64 = "fp64" if "cl_khr_fp64" in d.extensions else "no fp64"
            lines.append(
                f" {mark} {cl.device_type.to_string(d.type)}: {d.name.strip()} | {d.max_compute_units} CUs | "
                f"{d.global_mem_size / 2**30:.1f} GiB | {fp64} | {d.version}"
            )
    lines.append(f"chosen: {chosen.name.strip()}  (* above; set PYOPENCL_CTX to choose another)")
    for var in ("PYOPENCL_CTX", "POCL_AFFINITY", "POCL_MAX_PTHREAD_COUNT", "POCL_CACHE_DIR"):
        if os.environ.get(var):
            lines.append(f"{var}={os.environ[var]}")
    return "\n".join(lines)
