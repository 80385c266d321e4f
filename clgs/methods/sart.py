"""The ``sart`` method: SART / OS-SART of :mod:`clgs.ct.sart`."""
from __future__ import annotations

from clgs.ct.sart import sart
from clgs.progress import enabled


def run(scan, out_dir=None, iterations=None, subsets=None, relaxation=None, progress: bool = True) -> dict:
    """SART (``subsets`` = 1) or OS-SART (``subsets`` > 1), non-negative; unset options keep
    :func:`clgs.ct.sart.sart`'s defaults."""
    kwargs = {k: v for k, v in (("n_iter", iterations), ("subsets", subsets), ("relaxation", relaxation))
              if v is not None}
    with enabled(progress):
        return {"volume": sart(scan.projections, scan.geometry, verbose=progress, **kwargs)}
