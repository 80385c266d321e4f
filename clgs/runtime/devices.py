"""OpenCL devices: every candidate is tried with a probe kernel, and the first that works is used.

A driver can list a device and still be unable to compile for it (PoCL 3.0 from PyPI asks its
LLVM 14 for target CPU "generic" on AMD Zen 4/5 and fails every build), so a device is used only
after :func:`probe` has built ``cl/probe.cl`` (which includes the projector's own headers) on it,
run it and checked the numbers. The choice, in order:

1. ``use_device(spec)`` from Python, or ``clgs --device SPEC`` (which sets ``CLGS_DEVICE`` so
   that subprocesses and cluster workers inherit it);
2. ``PYOPENCL_CTX`` (pyopencl's own ``platform:device`` indices);
3. automatic: GPUs (most compute units x clock first), then CPU drivers in the order of
   :data:`CPU_PLATFORM_ORDER`, then anything else; the first that passes the probe.

A spec is ``P`` or ``P:D`` (platform and device indices, as ``clgs info`` numbers them) or a
piece of the platform's or device's name (``pocl``, ``intel``, ``nvidia``), case ignored. A
device named explicitly that fails the probe is an error with the reason, never a silent switch.
Contexts and queues are kept for the life of the process, one per device used, so switching back
and forth (the tests run every kernel on every working device) reuses compiled programs.
"""
from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from typing import Any

from clgs.errors import ClgsError

from . import drivers

try:
    import pyopencl as cl
except ImportError as exc:  # pragma: no cover - exercised only without pyopencl
    raise ImportError(
        "clgs needs pyopencl and an OpenCL driver; run the set-up in clgs's README "
        "(bash setup.sh), or: pip install pyopencl intel-opencl-rt intel-cmplr-lib-rt"
    ) from exc

#: CPU drivers in order of preference (a piece of the platform name, lower case).
CPU_PLATFORM_ORDER = ("portable computing language", "intel(r) opencl")

INSTALL_HINT = (
    "To get a working OpenCL device on Linux x86-64: run clgs's set-up (bash setup.sh), or install "
    "Debian's PoCL (apt-get install pocl-opencl-icd) or Intel's CPU runtime "
    "(pip install intel-opencl-rt intel-cmplr-lib-rt); for a GPU install its vendor's OpenCL driver (see docs/devices.md)."
)


class NoOpenCLDevice(ClgsError, RuntimeError):
    """No OpenCL device can run clgs's kernels (or the one asked for cannot): a
    :class:`~clgs.errors.ClgsError`, so the command line prints its message, not a traceback."""


@dataclass(frozen=True)
class Candidate:
    """One device as the ICD loader lists it, with what the probe found."""

    platform_index: int
    device_index: int
    platform: str
    name: str
    kind: str
    version: str
    error: str | None  # None: the probe passed; else its one-line reason
    device: Any = None  # the cl.Device

    @property
    def index(self) -> str:
        return f"{self.platform_index}:{self.device_index}"

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def label(self) -> str:
        return f"{self.platform.strip()} | {self.name.strip()}"


_lock = threading.RLock()
_devices: list[tuple[cl.Platform, cl.Device]] | None = None
_probes: dict = {}  # device int_ptr -> error or None
_contexts: dict = {}  # device int_ptr -> (context, queue)
_current: cl.Device | None = None


def _listed():
    """(platform, device) pairs as the ICD loader lists them; platforms that fail are skipped."""
    global _devices  # noqa: PLW0603 - the process-wide device list, read once
    if _devices is None:
        drivers.configure()  # the drivers' environment, before the ICD loader first runs
        try:
            platforms = cl.get_platforms()
        except cl.Error as exc:
            raise NoOpenCLDevice(f"No OpenCL platform found (pyopencl said: {exc}). {INSTALL_HINT}") from exc
        pairs: list = []
        for p in platforms:
            try:
                pairs.extend((p, d) for d in p.get_devices())
            except cl.Error:
                continue
        _devices = pairs
    return _devices


def _first_line(text: object) -> str:
    """The line of a build log that says what went wrong (an ``error:`` line when there is one)."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    for ln in lines:
        if "error" in ln.lower() and "build_program_failure" not in ln.lower():
            return ln[:200]
    return (lines[0] if lines else "unknown failure")[:200]


def probe(dev) -> str | None:
    """Build and run ``cl/probe.cl`` on ``dev``: None when it works, else the one-line reason.
    Cached per device for the life of the process."""
    key = dev.int_ptr
    with _lock:
        if key in _probes:
            return _probes[key]
    import numpy as np

    from .compiler import build, cl_source_dir

    error = None
    try:
        ctx = cl.Context([dev])
        queue = cl.CommandQueue(ctx)
        prog = build(ctx, (cl_source_dir() / "probe.cl").read_text(), ("-DREAL=float",))
        t = -np.linspace(0.0, 6.0, 64, dtype=np.float32)
        mf = cl.mem_flags
        tin = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=t)
        tout = cl.Buffer(ctx, mf.WRITE_ONLY, size=t.nbytes)
        prog.probe(queue, (t.size // 16,), None, tin, tout)
        out = np.empty_like(t)
        cl.enqueue_copy(queue, out, tout)
        queue.finish()
        want = np.exp2(t.astype(np.float64))
        worst = float(np.max(np.abs(out - want) / want))
        if not worst < 1e-6:
            error = f"wrong results from the probe kernel (relative error {worst:.1e})"
    except cl.Error as exc:  # build failures carry the log
        error = _first_line(exc)
    except Exception as exc:  # noqa: BLE001 - any failure of a driver is a reason to skip it
        error = f"{type(exc).__name__}: {_first_line(exc)}"
    with _lock:
        _probes[key] = error
    return error


def _kind(dev) -> str:
    for flag, name in ((cl.device_type.GPU, "GPU"), (cl.device_type.CPU, "CPU"), (cl.device_type.ACCELERATOR, "accelerator")):
        if dev.type & flag:
            return name
    return "other"


def candidates(run_probe: bool = True) -> list[Candidate]:
    """Every listed device with its probe result (``error`` is "not probed" without the probe)."""
    out = []
    platform_ids: dict = {}
    device_counts: dict = {}
    for p, d in _listed():
        pi = platform_ids.setdefault(p.int_ptr, len(platform_ids))
        di = device_counts.get(pi, 0)
        device_counts[pi] = di + 1
        error = probe(d) if run_probe else "not probed"
        out.append(Candidate(pi, di, p.name, d.name, _kind(d), p.version, error, d))
    return out


def _preference(pair) -> tuple:
    p, d = pair
    if d.type & cl.device_type.GPU:
        return (0, -d.max_compute_units * max(d.max_clock_frequency, 1))
    if d.type & cl.device_type.CPU:
        name = p.name.lower()
        rank = next((i for i, key in enumerate(CPU_PLATFORM_ORDER) if key in name), len(CPU_PLATFORM_ORDER))
        return (1, rank)
    return (2, 0)


def _matching(spec: str):
    """The listed (platform, device) pairs that ``spec`` names, in listing order."""
    pairs = _listed()
    spec = spec.strip()
    plats: list = []
    for p, _ in pairs:
        if p.int_ptr not in [q.int_ptr for q in plats]:
            plats.append(p)
    parts = spec.split(":")
    if all(part.strip().isdigit() for part in parts) and 1 <= len(parts) <= 2:
        pi = int(parts[0])
        if pi >= len(plats):
            raise NoOpenCLDevice(f"device {spec!r}: there is no platform {pi} (run 'clgs info' to list them)")
        devs = [d for p, d in pairs if p.int_ptr == plats[pi].int_ptr]
        if len(parts) == 2:
            di = int(parts[1])
            if di >= len(devs):
                raise NoOpenCLDevice(f"device {spec!r}: platform {pi} has no device {di} (run 'clgs info')")
            devs = [devs[di]]
        return [(plats[pi], d) for d in devs]
    needle = spec.lower()
    found = [(p, d) for p, d in pairs if needle in p.name.lower() or needle in d.name.lower()
             or needle in p.version.lower()]
    if not found:
        names = "; ".join(f"{p.name.strip()} | {d.name.strip()}" for p, d in pairs) or "none"
        raise NoOpenCLDevice(f"no OpenCL device matches {spec!r} (devices: {names}); run 'clgs info'")
    return found


def requested_spec() -> tuple[str, str] | None:
    """(where, spec) of the user's explicit choice, if any: ``CLGS_DEVICE``, then ``PYOPENCL_CTX``."""
    for var in ("CLGS_DEVICE", "PYOPENCL_CTX"):
        value = os.environ.get(var, "").strip()
        if value:
            return var, value
    return None


def _choose():
    """The device to use (see the module's docstring); raises NoOpenCLDevice with every reason."""
    asked = requested_spec()
    if asked is not None:
        var, spec = asked
        failures = []
        for _, d in _matching(spec):
            error = probe(d)
            if error is None:
                return d
            failures.append(f"{d.name.strip()}: {error}")
        raise NoOpenCLDevice(f"{var}={spec!r} names no working device ({'; '.join(failures)}). "
                             "Run 'clgs info' to see every device and why it fails, or unset it.")
    pairs = _listed()
    if not pairs:
        raise NoOpenCLDevice(f"OpenCL platforms exist but list no device. {INSTALL_HINT}")
    failures = []
    for p, d in sorted(pairs, key=_preference):
        error = probe(d)
        if error is None:
            return d
        failures.append(f"  {p.name.strip()} | {d.name.strip()}: {error}")
    raise NoOpenCLDevice("No OpenCL device can run clgs's kernels:\n" + "\n".join(failures) + "\n" + INSTALL_HINT)


def use_device(spec=None) -> cl.Device:
    """Make ``spec`` (a ``cl.Device``, a spec string, or None for the automatic choice) the
    process-wide device; operators made afterwards run on it. Returns the device."""
    global _current  # noqa: PLW0603 - the process-wide device choice
    with _lock:
        if spec is None:
            dev = _choose()
        elif isinstance(spec, cl.Device):
            error = probe(spec)
            if error is not None:
                raise NoOpenCLDevice(f"device {spec.name.strip()!r} fails the probe: {error}")
            dev = spec
        else:
            old = os.environ.get("CLGS_DEVICE")
            os.environ["CLGS_DEVICE"] = str(spec)
            try:
                dev = _choose()
            except Exception:
                if old is None:
                    os.environ.pop("CLGS_DEVICE", None)
                else:
                    os.environ["CLGS_DEVICE"] = old
                raise
        _current = dev
        return dev


def _entry():
    global _current  # noqa: PLW0603 - the process-wide device choice
    with _lock:
        if _current is None:
            _current = _choose()
        key = _current.int_ptr
        entry = _contexts.get(key)
        if entry is None:
            ctx = cl.Context([_current])
            entry = _contexts[key] = (ctx, cl.CommandQueue(ctx))
        return entry


def get_context() -> cl.Context:
    """The context of the process-wide device (chosen on first use)."""
    return _entry()[0]


def get_queue() -> cl.CommandQueue:
    """The in-order queue on the process-wide device."""
    return _entry()[1]


def device() -> cl.Device:
    return get_context().devices[0]


def is_cpu_device() -> bool:
    """True when device memory is host memory (buffers can wrap NumPy arrays without copies)."""
    return bool(device().type & cl.device_type.CPU)


def working_devices() -> list:
    """Every listed device that passes the probe, in listing order (the tests run on each)."""
    return [d for _, d in _listed() if probe(d) is None]


def device_label(dev=None) -> str:
    """``platform | device`` of ``dev`` (default: the current device), for tables and logs."""
    dev = dev or device()
    return f"{dev.platform.name.strip()} | {dev.name.strip()}"
