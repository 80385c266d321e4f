"""What ``clgs info`` prints about the OpenCL set-up: every device, its probe, the choice."""
from __future__ import annotations

import os

from . import devices


def describe() -> str:
    """Platforms and devices with their probe results, the chosen device, versions, settings."""
    import numpy as np
    import pyopencl as cl

    lines = [f"pyopencl {cl.VERSION_TEXT}, numpy {np.__version__}"]
    try:
        import torch

        lines.append(f"torch {torch.__version__}")
    except ImportError:
        lines.append("torch: not installed")
    try:
        found = devices.candidates()
    except devices.NoOpenCLDevice as exc:
        lines.append(str(exc))
        return "\n".join(lines)
    try:
        chosen = devices.device()
        chosen_error = ""
    except devices.NoOpenCLDevice as exc:
        chosen, chosen_error = None, str(exc)
    platform = None
    for c in found:
        if c.platform_index != platform:
            platform = c.platform_index
            lines.append(f"platform {c.platform_index}: {c.platform.strip()} ({c.version.strip()})")
        mark = "*" if chosen is not None and c.label == devices.device_label(chosen) else " "
        status = "works" if c.ok else f"FAILS: {c.error}"
        lines.append(f" {mark} {c.index} {c.kind}: {c.name.strip()} | {status}")
        if c.ok:
            d = c.device
            fp64 = "fp64" if "cl_khr_fp64" in d.extensions else "no fp64"
            lines.append(f"       {d.max_compute_units} compute units, {d.global_mem_size / 2**30:.1f} GiB, {fp64}, "
                         f"float vector width {d.native_vector_width_float}")
    if chosen is not None:
        lines.append(f"chosen: {devices.device_label(chosen)}  (* above; --device or CLGS_DEVICE / "
                     "PYOPENCL_CTX choose another: an index P:D or a piece of the name)")
    else:
        lines.append(chosen_error)
    for var in ("CLGS_DEVICE", "PYOPENCL_CTX", "OCL_ICD_VENDORS", "POCL_AFFINITY", "POCL_MAX_PTHREAD_COUNT",
                "POCL_CACHE_DIR"):
        if os.environ.get(var):
            lines.append(f"{var}={os.environ[var]}")
    return "\n".join(lines)
