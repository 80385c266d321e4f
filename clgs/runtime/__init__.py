"""The OpenCL runtime: drivers, device choice, compiled programs and buffers.

The only layer that sets up pyopencl. Importing it changes nothing in the process; the drivers'
environment (:mod:`.drivers`) is set when the devices are first listed, before the ICD loader
runs (``configure()`` does it earlier); :mod:`.devices` tries every device with a probe
kernel and picks the first that works (or the one the user named); :mod:`.programs` compiles and
caches the kernels; :mod:`.buffers` moves NumPy arrays in and out.
"""
import pyopencl as cl  # noqa: F401  (operators reach pyopencl through the runtime)

from .drivers import configure  # noqa: F401
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
from .programs import cl_source_dir, get_program, launch, real_name, round_up, shared, synchronous  # noqa: F401
from .report import describe  # noqa: F401
