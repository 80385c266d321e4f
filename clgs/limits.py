"""Bounds on the counts a user may ask for, shared by the settings' checks everywhere (the command
line, the methods' options, the settings dataclasses): beyond them a number is a typo (``1e23``),
not a plan, and is refused with the range instead of running for ever; and the machine's memory,
which sizes are checked against before any work. Imports only the standard library."""

import os

# training or SART iterations: R2-Gaussian's 30 000 takes hours on a CPU; ten million, years
MAX_ITERATIONS = 10_000_000


def total_memory() -> int | None:
    """Bytes of memory this machine has (None where unknown)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def available_memory() -> int | None:
    """Bytes of memory the system can give now (Linux ``MemAvailable``; None where unknown)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None
