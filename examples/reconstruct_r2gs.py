"""R2-Gaussian reconstruction from Python in a few lines.

    python examples/reconstruct_r2gs.py                 # a simulated head phantom, 10 views
    python examples/reconstruct_r2gs.py SCAN_DIR OUT    # your scan folder (clgs or R2-Gaussian)

The shell equivalent: ``clgs reconstruct SCAN_DIR --method r2gs --iterations 3000 --out OUT``.
Ctrl-C stops cleanly (outputs so far are written); run again with ``resume=True`` to continue.
"""
import sys

import numpy as np

from clgs import Scan, reconstruct_r2gs


def phantom_scan(n_views: int = 10, arc: float = np.pi) -> Scan:
    """A 64^3 Shepp-Logan-like head, its noisy cone-beam projections over ``arc`` radians.

    The truth is the voxel volume (each voxel the phantom's mean over it) and the projections are
    that volume's line integrals (Joseph's projector), as in R2-Gaussian's synthetic data and
    ``clgs ct simulate``: reconstruction and truth then describe the same object. (The phantom's
    analytic line integrals would describe a sharper object than its voxel means: a perfect
    reconstruction sampled at the voxel centres scores only 25 dB against them.)"""
    from clgs import CTProjector, Geometry, add_noise
    from clgs.ct import phantoms

    geo = Geometry.default(n_views=n_views, arc=arc, n_voxel=64, n_detector=128, volume_mm=256.0)
    truth = phantoms.voxelize(phantoms.head_phantom(geo), geo)
    projections = np.asarray(CTProjector(geo).forward(truth), np.float32)
    return Scan(geo, add_noise(projections, seed=0), truth)


if __name__ == "__main__":
    scan = Scan.load(sys.argv[1]) if len(sys.argv) > 1 else phantom_scan()
    out = sys.argv[2] if len(sys.argv) > 2 else "r2gs_run"
    result = reconstruct_r2gs(scan, out_dir=out, iterations=3000, n_gaussians=20_000, log_every=250)
    print(result.summary)
    print(f"volume {result.volume.shape}, max {np.max(result.volume):.4f} /mm; "
          f"{result.trainer.n_gaussians} Gaussians; files: {', '.join(str(p) for p in result.files.values())}")
