"""Simulate a held-out femur whose densities are not the ones the density atlas was built from.

    python3 examples/femur_density_shift.py shifted24/ --subject 24 --angles ap-lat
    clgs femur reconstruct shifted24 --out r --set iterations=1000 --set lambda_density=2

The plugin's held-out subjects get their CT from the same phantom as the twenty that built the
atlas, so a density prior fitted on them is judged on densities the atlas already knows. Here the
subject's bone (voxels above ``--bone-above``, 1/mm) is scaled by ``--bone``, the rest by
``--tissue``, and the whole volume by a smooth random field of +-``--field`` (a Gaussian-filtered
noise, ``--seed``); the scan is then simulated as the experiment does (the same grid, noise).
"""
import argparse
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi

from clgs.anatomy.plugins import get_anatomy
from clgs.anatomy.simulation import simulate_subject
from clgs.anatomy.views import CLINICAL_SETS


def shifted_volume(volume, bone_above: float, bone: float, tissue: float, field: float, seed: int,
                   sigma_voxels: float = 8.0) -> np.ndarray:
    """The volume with its bone scaled by ``bone``, the rest by ``tissue``, all by ``1 + field * f``
    (``f`` a smooth random field scaled to a largest magnitude of 1)."""
    v = np.asarray(volume, np.float32)
    out = np.where(v > bone_above, bone * v, tissue * v)
    if field:
        f = ndi.gaussian_filter(np.random.default_rng(seed).standard_normal(v.shape).astype(np.float32), sigma_voxels)
        out = out * (1.0 + field * f / max(float(np.abs(f).max()), 1e-12))
    return out.astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="scan folder to write")
    ap.add_argument("--subject", default="24", help="held-out subject [default: 24]")
    views = ap.add_mutually_exclusive_group()
    views.add_argument("--views", type=int, default=None, help="views over a half-turn [default: 5]")
    views.add_argument("--angles", choices=sorted(CLINICAL_SETS), default=None, help="a named view set instead")
    ap.add_argument("--bone-above", type=float, default=0.025, help="bone: voxels above this, 1/mm [default: 0.025]")
    ap.add_argument("--bone", type=float, default=1.2, help="bone density factor [default: 1.2]")
    ap.add_argument("--tissue", type=float, default=0.85, help="density factor of the rest [default: 0.85]")
    ap.add_argument("--field", type=float, default=0.10, help="smooth field's largest relative change [default: 0.10]")
    ap.add_argument("--seed", type=int, default=7, help="seed of the smooth field [default: 7]")
    args = ap.parse_args()
    if min(args.bone, args.tissue) <= 0 or not 0 <= args.field < 1:
        ap.error("--bone and --tissue must be > 0 and --field in [0, 1)")
    femur = get_anatomy("femur")
    held_out = [str(s) for s in femur.test_subjects()]
    if args.subject not in held_out:
        ap.error(f"--subject must be a held-out subject ({', '.join(held_out)}), got {args.subject!r}")
    subject = femur.load_subject(args.subject)
    subject.volume = shifted_volume(subject.volume, args.bone_above, args.bone, args.tissue, args.field, args.seed)
    kw = {"angles": np.radians(CLINICAL_SETS[args.angles])} if args.angles else {"n_views": args.views or 5}
    scan = simulate_subject(femur, subject, protocol="same", **kw)
    scan.save(args.out, overwrite=True)
    print(f"{args.out}: subject {args.subject}, {scan.geometry.n_views} views, bone x{args.bone}, the rest "
          f"x{args.tissue}, a smooth field of +-{args.field:.0%}")


if __name__ == "__main__":
    main()
