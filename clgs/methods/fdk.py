"""The ``fdk`` method: FDK (cone beam) or FBP (parallel beam) of :mod:`clgs.ct.fdk`."""
from __future__ import annotations

from clgs.ct.fdk import fdk


def run(scan, out_dir=None, filter: str = "ram-lak", short_scan="auto") -> dict:
    """Feldkamp-Davis-Kress (FBP for parallel beam), with redundancy weights for short arcs."""
    short_scan = {"on": True, "off": False}.get(short_scan, short_scan)
    return {"volume": fdk(scan.projections, scan.geometry, filter=filter, short_scan=short_scan)}
