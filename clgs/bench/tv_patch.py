"""``clgs bench tv-patch``: the TV patch of a training step, fused (``clgs.fit.tv_patch``) against the
unfused path (``tv3d`` of ``Backend.voxelize_shared``), side by side in one process.

Scene: the Gaussians of the ``clgs bench train`` model (default 50 000, 3-sigma radii of about 2-8
detector pixels, in a 128^3 volume; ``scene``), precisions and half-widths built once as the step's
projection builds them. Each repeat draws a random 32^3 patch and times both paths on it, forward and backward
down to means, precisions and densities (the same patches, alternating, so machine load hits both
alike). Prints medians, 90th percentiles and their ratio, and checks that both paths agree.
"""
from __future__ import annotations

import click


def scene(n: int = 50_000, seed: int = 0):
    """(volume grid in scene units, means, scales, quats, densities as float32 tensors): the Gaussians
    of ``clgs bench train``'s scene (uniform in the central 80% of a 128^3 volume of 256 mm, 3-sigma
    radii of 2-8 pixels of a 256^2 cone-beam detector, random rotations), without its projections."""
    import numpy as np
    import torch

    from clgs.geometry import Geometry

    geo = Geometry.default(n_views=50, n_voxel=128, n_detector=256, volume_mm=256.0, mode="cone")
    rng = np.random.default_rng(seed)
    box = 0.5 * geo.sVoxel[::-1] * geo.scale
    px = geo.DSD / geo.DSO / (geo.dDetector[1] * geo.scale)  # detector pixels per scene unit at the axis
    means = (rng.random((n, 3)) * 1.6 - 0.8) * box
    scales = rng.uniform(2.0, 8.0, (n, 1)) / 3.0 / px * rng.uniform(0.7, 1.3, (n, 3))
    quats = rng.normal(size=(n, 4))
    dens = rng.uniform(0.2, 1.0, n)
    return (geo.volume_grid(scene=True), *(torch.tensor(a, dtype=torch.float32) for a in (means, scales, quats, dens)))


def compare(n: int = 50_000, repeats: int = 100, size: int = 32, seed: int = 0) -> dict:
    """Seconds per patch (forward + backward) of both paths: {"old": [...], "new": [...]} and the
    largest relative differences of the TV value and the gradients seen."""
    import time

    import torch

    from clgs.fit import losses as L
    from clgs.fit.trainer import Backend
    from clgs.fit.tv_patch import tv_patch
    from clgs.ops.voxelizer import cov_prec

    grid, means, scales, quats, dens = scene(n, seed)
    with torch.no_grad():
        _, prec, extent = cov_prec(scales, quats, cov=False, extent=True)
    gen = torch.Generator().manual_seed(seed)
    blocks = [L.random_block(grid, size, gen) for _ in range(repeats + 3)]
    leaves = {k: [t.detach().clone().requires_grad_(True) for t in (means, prec, dens)] for k in ("old", "new")}
    paths = {
        "old": lambda b, v: L.tv3d(Backend.voxelize_shared(v[0], v[1], v[2], extent, b)),
        "new": lambda b, v: tv_patch(v[0], v[1], v[2], extent, b),
    }
    times = {"old": [], "new": []}
    worst = {"tv": 0.0, "grad": 0.0}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the trainer runs with the OpenCL backend
    try:
        for i, b in enumerate(blocks):
            values = {}
            for name in (("old", "new") if i % 2 == 0 else ("new", "old")):
                v = leaves[name]
                for t in v:
                    t.grad = None
                t0 = time.perf_counter()
                out = paths[name](b, v)
                (0.05 * out).backward()
                dt = time.perf_counter() - t0
                if i >= 3:
                    times[name].append(dt)
                values[name] = (float(out.detach()), [t.grad for t in v])
            (a, ga), (c, gc) = values["old"], values["new"]
            worst["tv"] = max(worst["tv"], abs(a - c) / max(abs(a), 1e-30))
            for x, y in zip(ga, gc):
                worst["grad"] = max(worst["grad"], float((x - y).abs().max()) / max(float(x.abs().max()), 1e-30))
    finally:
        torch.set_num_threads(threads)
    return {"times": times, "worst": worst}


@click.command()
@click.option("--gaussians", "n", default=50_000, show_default=True)
@click.option("--repeats", default=100, show_default=True, help="patches timed (each by both paths)")
@click.option("--size", default=32, show_default=True, help="patch side in voxels")
@click.option("--seed", default=0, show_default=True)
def main(n, repeats, size, seed):
    """TV patch: fused against unfused, ms per patch (forward + backward), same patches."""
    import os

    import numpy as np

    res = compare(n, repeats, size, seed)
    t = {k: np.asarray(v) * 1e3 for k, v in res["times"].items()}
    click.echo(f"{n} Gaussians, random {size}^3 patches of a 128^3 volume, {repeats} each; load average "
               f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    click.echo(f"{'path':34s}{'median ms':>10s}{'p90 ms':>10s}")
    for k, label in (("old", "tv3d(Backend.voxelize_shared) (old)"), ("new", "tv_patch (fused)")):
        click.echo(f"{label:34s}{np.median(t[k]):10.2f}{np.percentile(t[k], 90):10.2f}")
    click.echo(f"speed-up (median): {np.median(t['old']) / np.median(t['new']):.2f}x; largest relative difference: "
               f"TV {res['worst']['tv']:.1e}, gradients {res['worst']['grad']:.1e}")
