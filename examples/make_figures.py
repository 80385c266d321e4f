"""Pictures for the README: a simulated femur CT (slices) and its cone-beam projections.

    python examples/make_figures.py [--subject 20] [--out docs/img]

Writes ``femur_ct_slices.png`` (axial, coronal and sagittal slices of a held-out subject's
simulated CT, in 1/mm at 70 keV), ``femur_atlas.png`` (mean and standard deviation of the
density atlas, when the femur model has been built) and ``femur_projections.png`` (line
integrals at a few angles over the default 180 degree arc, with the CT projector); a missing
model or projector skips its figure with a note.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np


def slice_montage(volume, spacing_zyx, path, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nz, ny, nx = volume.shape
    dz, dy, dx = spacing_zyx
    bone = volume > 0.03
    kk, jj, ii = np.nonzero(bone)
    j_c, i_c = int(np.median(jj)), int(np.median(ii))
    zs = [int(np.percentile(kk, q)) for q in (8, 50, 92)]
    vmin, vmax = 0.0, 0.055
    fig = plt.figure(figsize=(12, 7.2), constrained_layout=True)
    grid = fig.add_gridspec(3, 3, width_ratios=[1, 1, 1])
    for r, k in enumerate(zs[::-1]):
        ax = fig.add_subplot(grid[r, 0])
        ax.imshow(volume[k], cmap="gray", vmin=vmin, vmax=vmax, origin="lower", extent=(0, nx * dx, 0, ny * dy))
        ax.set_title(f"axial, z = {k * dz:.0f} mm", fontsize=9)
        ax.axis("off")
    ax = fig.add_subplot(grid[:, 1])
    ax.imshow(volume[:, j_c, :], cmap="gray", vmin=vmin, vmax=vmax, origin="lower", extent=(0, nx * dx, 0, nz * dz))
    ax.set_title("coronal", fontsize=9)
    ax.axis("off")
    ax = fig.add_subplot(grid[:, 2])
    im = ax.imshow(volume[:, :, i_c], cmap="gray", vmin=vmin, vmax=vmax, origin="lower",
                   extent=(0, ny * dy, 0, nz * dz))
    ax.set_title("sagittal", fontsize=9)
    ax.axis("off")
    fig.colorbar(im, ax=ax, fraction=0.08, label="attenuation (1/mm, 70 keV)")
    fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def projection_montage(projections, angles, path, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(projections)
    fig, axes = plt.subplots(1, n, figsize=(2.6 * n, 5.6), constrained_layout=True)
    vmax = float(projections.max())
    for ax, p, a in zip(np.atleast_1d(axes), projections, angles):
        im = ax.imshow(p, cmap="gray", vmin=0, vmax=vmax, origin="lower")
        ax.set_title(f"{np.rad2deg(a):.0f} deg", fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes, fraction=0.03, label="line integral")
    fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def atlas_figure(mean, var, spacing_zyx, path):
    """Coronal and sagittal slices of the density atlas: mean and standard deviation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nz, ny, nx = mean.shape
    dz, dy, dx = spacing_zyx
    kk, jj, ii = np.nonzero(mean > 0.03)
    j_c, i_c = int(np.median(jj)), int(np.median(ii))
    sd = np.sqrt(np.maximum(var, 0))
    fig, axes = plt.subplots(1, 4, figsize=(11, 7), constrained_layout=True)
    panels = [(mean[:, j_c, :], (0, nx * dx), "mean, coronal", 0.055),
              (mean[:, :, i_c], (0, ny * dy), "mean, sagittal", 0.055),
              (sd[:, j_c, :], (0, nx * dx), "std. dev., coronal", float(sd.max())),
              (sd[:, :, i_c], (0, ny * dy), "std. dev., sagittal", float(sd.max()))]
    for ax, (img, ext, title, vmax) in zip(axes, panels):
        im = ax.imshow(img, cmap="gray" if "mean" in title else "magma", vmin=0, vmax=vmax, origin="lower",
                       extent=(*ext, 0, nz * dz))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.08, shrink=0.6)
    fig.suptitle("femur density atlas (20 subjects warped to the template; 1/mm at 70 keV)", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subject", default="20", help="femur subject id (20-25 are held out)")
    ap.add_argument("--out", default=os.path.join("docs", "img"))
    ap.add_argument("--views", type=int, default=5, help="projections shown")
    args = ap.parse_args(argv)

    import clgs_femur

    pop = clgs_femur.population_model()
    os.makedirs(args.out, exist_ok=True)
    t0 = time.perf_counter()
    subject = pop.load_subject(args.subject)
    print(f"simulated femur {args.subject}: {subject.volume.shape} voxels of {subject.spacing[0]:.1f} mm "
          f"in {time.perf_counter() - t0:.1f} s")
    slices = os.path.join(args.out, "femur_ct_slices.png")
    slice_montage(subject.volume, subject.spacing, slices,
                  f"simulated CT, LLP26 femur {args.subject} (held out)" if args.subject in pop.test_ids
                  else f"simulated CT, LLP26 femur {args.subject}")
    print(f"wrote {slices}")
    if os.path.exists(pop.model_path):  # the density atlas, when the model has been built
        from clgs.shape.model import load_model

        _, atlas = load_model(pop.model_path, need_shape_model=False)
        path = os.path.join(args.out, "femur_atlas.png")
        atlas_figure(atlas.mean, atlas.var, subject.spacing, path)
        print(f"wrote {path}")
    else:
        print(f"no femur model at {pop.model_path} yet (clgs femur build-model): atlas figure skipped")
    try:
        from clgs import CTProjector
    except ImportError as exc:
        print(f"no CT projector ({exc}): projection figure skipped")
        return
    geo = pop.geometry(n_views=args.views, arc=np.pi)
    t0 = time.perf_counter()
    proj = np.asarray(CTProjector(geo).forward(subject.volume))
    print(f"{args.views} projections {geo.nDetector} in {time.perf_counter() - t0:.1f} s")
    path = os.path.join(args.out, "femur_projections.png")
    projection_montage(proj, geo.angles, path,
                       f"cone-beam projections (DSO {geo.DSO:.0f} mm, DSD {geo.DSD:.0f} mm, 0-180 deg)")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
