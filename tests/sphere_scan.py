"""A tiny simulated scan of a uniform ball (noise-free, exact projector): the smallest input that
every method runs on in seconds, for tests of the machinery around the methods."""
import numpy as np

from clgs.geometry import Geometry
from clgs.io.scan import Scan


def sphere_scan(n: int, views: int, detector: int, volume_mm: float, radius2: float) -> Scan:
    """An ``n``^3 ball of 0.02 /mm (``radius2``: squared radius in voxels) seen in ``views`` views."""
    from clgs.ops.ct_projector import CTProjector

    geo = Geometry.default(n_views=views, n_voxel=n, n_detector=detector, volume_mm=volume_mm)
    zz, yy, xx = np.mgrid[:n, :n, :n] - (n - 1) / 2
    truth = np.where(zz ** 2 + yy ** 2 + xx ** 2 < radius2, 0.02, 0.0).astype(np.float32)
    return Scan(geo, np.asarray(CTProjector(geo).forward(truth), np.float32), truth=truth)
