"""What else the machine did while a benchmark ran. On a shared virtual machine the host can take
CPU time away ("steal") while the load average stays low, and every figure slows with it; the
benchmarks print both next to their figures. Neither catches every slow spell (cores shared
with other guests slow a run without steal: seen here at 0-9 % steal and half speed), so the
kernel benchmark's exp probe, against its quiet figure, is the better gauge of the machine."""
from __future__ import annotations

import os


def _cpu_times():
    """The aggregate ``cpu`` line of /proc/stat (jiffies), or None where there is none."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    return [int(x) for x in fields[1:]]


class HostWatch:
    """Started when made; :meth:`summary` describes the machine over the time since."""

    def __init__(self):
        self._start = _cpu_times()

    def stolen(self) -> float | None:
        """Share of all CPU time since the start that the hypervisor gave to others (0-1)."""
        end = _cpu_times()
        if self._start is None or end is None or len(end) < 8:
            return None
        delta = [b - a for a, b in zip(self._start, end)]
        total = sum(delta[:8])  # user .. steal (guest time is already inside user)
        return delta[7] / total if total > 0 else None

    def summary(self) -> str:
        try:
            load = f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
        except (AttributeError, OSError):
            load = f"{os.cpu_count()} cores"
        steal = self.stolen()
        if steal is None:
            return f"machine during the run: {load}"
        return (f"machine during the run: {load}; {100 * steal:.0f}% of the CPU time went to other "
                f"virtual machines (steal; a shared host can also run slow without any)")
