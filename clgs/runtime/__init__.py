"""The OpenCL runtime: drivers, device choice, compiled programs and buffers.

The only layer that sets up pyopencl. Importing it changes nothing in the process; the drivers'
environment (:mod:`.drivers`) is set when the devices are first listed, before the ICD loader
runs (``configure()`` does it earlier); :mod:`.devices` tries every device with a probe
kernel and picks the first that works (or the one the user named); :mod:`.programs` compiles and
caches the kernels (:mod:`.compiler` builds them) and holds the one launch helper;
:mod:`.buffers` moves NumPy arrays in and out; :mod:`.operator` is the contract every OpenCL
operator of :mod:`clgs.ops` follows.
"""
import pyopencl as cl  # noqa: F401  (operators reach pyopencl through the runtime)

from .compiler import cl_source_dir  # noqa: F401
from .devices import (  # noqa: F401
    NoOpenCLDevice,
    candidates,
    device,
    device_label,
    get_context,
    get_queue,
    is_cpu_device,
    probe,
    use_device,
    working_devices,
)
from .drivers import configure  # noqa: F401
from .operator import Operator, context_and_queue  # noqa: F401
from .programs import get_program, launch, real_name, round_up, shared, synchronous  # noqa: F401
from .report import describe  # noqa: F401
