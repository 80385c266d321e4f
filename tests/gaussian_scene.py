"""The tiny training scene of the trainer, schedule and benchmark tests: 6 anisotropic Gaussians
(attenuation about 0.01-0.02 /mm) in a 64 mm cube, seen by 8 cone-beam views of 24^2 pixels,
with its truth voxelised on a 16^3 grid."""
import numpy as np
import torch

from clgs.geometry import Geometry
from clgs.io.scan import Scan


def six_gaussian_scan() -> Scan:
    from clgs.ops.projector import project
    from clgs.ops.voxelizer import voxelize

    geo = Geometry.default(n_views=8, n_voxel=16, n_detector=24, volume_mm=64.0)
    rng = np.random.default_rng(0)
    n = 6
    m = torch.tensor(rng.uniform(-0.4, 0.4, (n, 3)), dtype=torch.float32)
    s = torch.tensor(rng.uniform(0.1, 0.25, (n, 3)), dtype=torch.float32)
    q = torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32)
    d = torch.tensor(rng.uniform(0.01, 0.02, n), dtype=torch.float32)
    with torch.no_grad():
        proj = project(m, s, q, d, geo, list(range(geo.n_views))).numpy()
        truth = voxelize(m, s, q, d, geo.volume_grid()).numpy()
    return Scan(geo, proj, truth)
