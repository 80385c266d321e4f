"""Voxelizer figures for ``clgs bench kernels``: our OpenCL ops against plain torch, same run.

Scene: N Gaussians (10k and 50k) with centres uniform in [-0.8, 0.8]^3, standard deviations
0.5-2 voxels of a 128^3 grid over [-1, 1]^3 (3-sigma boxes 3-12 voxels wide), random rotations,
densities 0.01-0.1; float32. Cases, each timed through the public autograd ops
(``clgs.ops.voxelizer.voxelize`` / ``voxelize_points``, i.e. including the torch-side precision and
checks):

* ``grid 128^3 forward``: the whole grid.
* ``block 32^3 forward`` / ``block 32^3 backward``: a random 32^3 block (a new one each repeat),
  as for a TV or density-prior patch; backward = ``loss.backward()`` after the forward, down to
  means, scales, quaternions and densities.
* ``points forward``: the field at the N Gaussian centres (the overlap count of the shape-guided
  initialisation queries the field at the reference centres).

Baseline: ``clgs.reference.voxelization`` in torch on the same CPU: the windowed version (each
Gaussian evaluated on its own box, scatter-added) for grids and blocks, the KD-tree version
(scipy ball queries for the candidate pairs, then torch) for points. The full-grid baseline would
take minutes, so it is timed on a subset of the Gaussians (``ref_subset``) and scaled linearly
(its cost is linear in their number); such rows say ``ref_scaled: True``.

Each row is a dict: ``case``, ``gaussians``, ``ms`` (median), ``ref_ms``, ``speedup``
(ref_ms / ms), ``ref_scaled``, ``ref_subset``.
"""
from __future__ import annotations

import time


def _scene(n, seed=0):
    import torch

    g = torch.Generator().manual_seed(seed)
    h = 2.0 / 128
    means = torch.rand(n, 3, generator=g) * 1.6 - 0.8
    scales = h * (0.5 + 1.5 * torch.rand(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    rho = 0.01 + 0.09 * torch.rand(n, generator=g)
    return means, scales, quats, rho


def _median(times):
    times = sorted(times)
    return times[len(times) // 2]


def _time(fn, repeat, warm=True):
    if warm:
        fn(0)
    out = []
    for r in range(repeat):
        t = time.perf_counter()
        fn(r + 1)
        out.append(time.perf_counter() - t)
    return _median(out) * 1e3


def rows(quick: bool) -> list[dict]:
    """Benchmark rows (see the module docstring); ``quick`` uses fewer repeats and smaller
    baseline subsets."""
    import numpy as np
    import torch

    from clgs.geometry import Grid
    from clgs.ops.voxelizer import voxelize, voxelize_points
    from clgs.reference import voxelization as ref

    repeat = 3 if quick else 7
    grid = Grid((128,) * 3, (-1 + 1 / 128,) * 3, (2 / 128,) * 3)
    rng = np.random.default_rng(0)
    blocks = [grid.block(rng.integers(0, 128 - 32 + 1, 3), (32, 32, 32)) for _ in range(repeat + 1)]
    out = []
    torch.set_grad_enabled(True)
    for n in (10_000, 50_000):
        means, scales, quats, rho = _scene(n)

        def row(case, ms, ref_ms, subset):
            out.append({"case": case, "gaussians": n, "ms": round(ms, 3), "ref_ms": round(ref_ms, 1),
                        "speedup": round(ref_ms / ms, 1), "ref_scaled": subset is not None and subset < n,
                        "ref_subset": subset})

        # whole grid
        ms = _time(lambda r: voxelize(means, scales, quats, rho, grid), repeat)
        sub = min(n, 1000 if quick else 4000)
        ref_ms = _time(lambda r: ref.voxelize_windowed(means[:sub], scales[:sub], quats[:sub], rho[:sub], grid),
                       1, warm=False) * n / sub
        row("grid 128^3 forward", ms, ref_ms, sub)

        # random 32^3 blocks: forward, then backward of a weighted sum
        params = [t.clone().requires_grad_() for t in (means, scales, quats, rho)]
        weights = torch.randn(32, 32, 32, generator=torch.Generator().manual_seed(1))
        ms = _time(lambda r: voxelize(*params, blocks[r]), repeat)
        ref_ms = _time(lambda r: ref.voxelize_windowed(means, scales, quats, rho, blocks[r]), max(1, repeat // 2))
        row("block 32^3 forward", ms, ref_ms, None)

        def backward(fn):
            def run(r):
                loss = (fn(*params, blocks[r]) * weights).sum()
                t = time.perf_counter()
                loss.backward()
                run.times.append(time.perf_counter() - t)
                for p in params:
                    p.grad = None
            run.times = []
            return run

        run = backward(voxelize)
        _time(run, repeat)
        ms = _median(run.times[1:]) * 1e3
        run = backward(ref.voxelize_windowed)
        _time(run, max(1, repeat // 2))
        row("block 32^3 backward", ms, _median(run.times[1:]) * 1e3, None)

        # the field at the Gaussian centres
        ms = _time(lambda r: voxelize_points(means, scales, quats, rho, means), repeat)
        ref_ms = _time(lambda r: ref.voxelize_points_kdtree(means, scales, quats, rho, means), 1)
        row(f"points forward ({n // 1000}k points)", ms, ref_ms, None)
    return out


if __name__ == "__main__":  # python -m clgs.bench.voxelizer_rows
    import sys

    for r in rows(quick="--quick" in sys.argv):
        print(r)
