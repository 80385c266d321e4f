"""Compiled programs, kernel launches and process-wide operator instances.

A program is compiled once per (context, source file, ``-D`` options) and its kernel objects are
reused: PoCL recompiles on the first launch of each kernel, so re-creating them is costly.
"""
from __future__ import annotations

import threading

import numpy as np
import pyopencl as cl

from .compiler import build, cl_source_dir
from .devices import get_context

_lock = threading.Lock()
_programs: dict = {}


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
    defines = defines or {}
    for key in sorted(defines):
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
        self.ctx = ctx  # kept alive with the program, so its handle (the cache key) is never reused
        self.options = options
        self._program = build(ctx, source, options)
        self._kernels: dict = {}

    def kernel(self, name: str) -> cl.Kernel:
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
    key = (ctx.int_ptr, filename, options)
    with _lock:
        prog = _programs.get(key)
    if prog is None:
        source = (cl_source_dir() / filename).read_text()
        prog = Program(ctx, source, options)
        with _lock:
            _programs[key] = prog
    return prog


_launch_lock = threading.Lock()
_declared: dict = {}  # id(kernel) -> True: scalar types declared; False: set changed arguments one by one
_kernel_args: dict = {}  # id(kernel) -> the arguments it was last launched with (kernels are cached)
_synchronous = [0]  # > 0: every launch waits for its kernel (profiling)


def _declare_scalars(kernel, args) -> bool:
    """Tell pyopencl the kernel's scalar argument types (from the NumPy scalars of its first
    launch): its argument setter then packs all of them at once, about 6 us for twenty arguments
    where setting one NumPy scalar alone costs 10-15 us. False (nothing declared) when an
    argument is a plain Python number, whose type the kernel cannot be told from it."""
    dtypes: list = []
    for a in args:
        if isinstance(a, cl.MemoryObjectHolder):
            dtypes.append(None)
        elif isinstance(a, np.generic):
            dtypes.append(a.dtype)
        else:
            return False
    kernel.set_scalar_arg_dtypes(dtypes)
    return True


class synchronous:
    """Within this block every kernel launch waits until its kernel has run. Kernels are queued
    without waiting otherwise, so a profile charges a kernel's time to whichever later call first
    waits on the queue; under this block it lands on the operator that launched it (profiles only:
    it removes the overlap of host and device work)."""

    def __enter__(self):
        with _launch_lock:
            _synchronous[0] += 1
        return self

    def __exit__(self, *exc):
        with _launch_lock:
            _synchronous[0] -= 1
        return False


def launch(queue, kernel, gsize, lsize, *args):
    """Enqueue ``kernel`` on ``queue`` with ``args``: the one way every operator launches a
    kernel (:meth:`clgs.runtime.operator.Operator.launch` adds the profiling hook). The first
    launch of a kernel declares its scalar types, so later launches pack every argument in one
    call; a kernel first launched with a plain Python number instead gets only the arguments that
    changed since its last launch set (the same buffer object, or an equal scalar of the same
    type, is kept). Kernels are cached per program and shared, hence one module-wide record.
    Returns the event."""
    key = id(kernel)
    with _launch_lock:
        declared = _declared.get(key)
        if declared is None:
            declared = _declared[key] = _declare_scalars(kernel, args)
        if declared:
            kernel.set_args(*args)
        else:
            last = _kernel_args.get(key)
            if last is None or len(last) != len(args):
                last = _kernel_args[key] = [None] * len(args)
            for i, v in enumerate(args):
                old = last[i]
                if old is v:
                    continue
                if isinstance(v, cl.MemoryObjectHolder) or old is None or type(old) is not type(v) or old != v:
                    kernel.set_arg(i, v)
                last[i] = v
        event = cl.enqueue_nd_range_kernel(queue, kernel, gsize, lsize)
        if _synchronous[0]:
            event.wait()
        return event


_shared: dict = {}
_shared_lock = threading.Lock()


def shared(cls):
    """The process-wide instance of ``cls`` on the current device (an operator class: its compiled
    programs and pooled buffers then serve every call), made on first use."""
    key = (cls, id(get_context()))
    with _shared_lock:
        obj = _shared.get(key)
        if obj is None:
            obj = _shared[key] = cls()
        return obj
