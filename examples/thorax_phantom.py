"""TIGRE's 128^3 thorax phantom as a NIfTI volume that `clgs simulate` reads.

    python examples/thorax_phantom.py img128.mat thorax128.nii.gz
    clgs simulate thorax128.nii.gz --views 25 --arc 360 --out chest25

The phantom is a segmented human thorax with piecewise-constant attenuation (1/mm; lungs, soft
tissue, vessels, bone), distributed with the TIGRE toolbox under its BSD licence. Download
``img128.mat`` from TIGRE's repository at commit de4feb89 (the file was removed from later
versions):

    https://raw.githubusercontent.com/CERN/TIGRE/de4feb89fad1495606f903c9dadc39986cba4f0c/Test_data/Thorax-phantom/img128.mat

TIGRE's default geometry puts the 128^3 volume in a 256 mm cube, so the voxels are 2 mm. The
array is written as it is stored (its first axis the NIfTI's i); clgs keeps that order in every
volume it writes from this input. docs/schedules.md uses it for R2-Gaussian mode's convergence.
"""
import argparse

import nibabel as nib
import numpy as np
import scipy.io


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mat", help="img128.mat from TIGRE's repository")
    ap.add_argument("out", help="NIfTI file to write (.nii or .nii.gz)")
    ap.add_argument("--voxel-mm", type=float, default=2.0, help="voxel size (TIGRE's default geometry: 2 mm)")
    args = ap.parse_args()
    data = scipy.io.loadmat(args.mat)  # a MATLAB file: arrays only, no code runs
    if "img" not in data:
        names = ", ".join(k for k in data if not k.startswith("__"))
        raise SystemExit(f"{args.mat} holds no 'img' array (it has: {names})")
    img = np.asarray(data["img"], np.float32)
    if img.ndim != 3 or not np.isfinite(img).all() or img.min() < 0:
        raise SystemExit(f"{args.mat}: expected a finite, non-negative 3D volume, got shape {img.shape}")
    nib.save(nib.Nifti1Image(img, np.diag([args.voxel_mm] * 3 + [1.0])), args.out)
    print(f"wrote {args.out}: {img.shape} voxels of {args.voxel_mm} mm, "
          f"attenuation {img.min():.4g}-{img.max():.4g} 1/mm")


if __name__ == "__main__":
    main()
