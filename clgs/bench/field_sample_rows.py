"""Deformation figures for ``clgs bench kernels``: the shape model's exp(v) and the field at the
template points, OpenCL (``clgs.ops.field_sampler``) against torch's ``grid_sample``, same run.

Scene: a smooth random velocity field on the femur model's grid (64 x 33 x 38 cells of 7.6 mm),
up to about 1.5 cells, so that the shape-guided set's rule takes 2 squarings as in training;
35k points spread over the grid (the shape-guided Gaussians' reference centres). Cases, timed
through the public autograd ops (``clgs.shape.model.exp_velocity`` and ``sample_field``):

* ``exp(v) forward`` and ``exp(v) forward+backward`` (backward of a weighted sum, down to v);
* ``field at 35k points forward+backward``.

Each row is a dict: ``case``, ``ms`` (median of the OpenCL path), ``ref_ms`` (torch), ``speedup``.
"""
from __future__ import annotations

import time

SHAPE = (64, 33, 38)
SPACING = (7.6, 7.6, 7.6)  # z, y, x mm


def _median_ms(fn, repeat):
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return sorted(times)[len(times) // 2] * 1e3


def rows(quick: bool) -> list[dict]:
    import torch
    import torch.nn.functional as F

    from clgs.ops.field_sampler import default_sampler
    from clgs.shape.model import exp_velocity, sample_field

    g = torch.Generator().manual_seed(0)
    noise = torch.randn((3, *SHAPE), generator=g)[None]
    v = F.avg_pool3d(F.avg_pool3d(noise, 5, 1, 2), 5, 1, 2)[0]
    v = (v * (1.5 * SPACING[0] / float(v.abs().max()))).requires_grad_(True)
    extent = torch.tensor([(n - 1) * d for n, d in zip(SHAPE[::-1], SPACING[::-1])])
    points = torch.rand((35_000, 3), generator=g) * extent
    weights = torch.randn((3, *SHAPE), generator=g)
    repeat = 5 if quick else 20
    samplers = {"cl": default_sampler(), "torch": None}

    def exp_fwd(s):
        with torch.no_grad():
            exp_velocity(v, SPACING, min_squarings=2, sampler=s)

    def exp_both(s):
        (exp_velocity(v, SPACING, min_squarings=2, sampler=s) * weights).sum().backward()
        v.grad = None

    def at_points(s):
        u = v.detach().clone().requires_grad_(True)
        sample_field(u, points, SPACING, (0.0, 0.0, 0.0), sampler=s).sum().backward()

    out = []
    for name, fn in (("exp(v) forward", exp_fwd), ("exp(v) forward+backward", exp_both),
                     ("field at 35k points forward+backward", at_points)):
        ms = _median_ms(lambda: fn(samplers["cl"]), repeat)
        ref = _median_ms(lambda: fn(samplers["torch"]), repeat)
        out.append({"case": name, "ms": ms, "ref_ms": ref, "speedup": ref / ms})
    return out


if __name__ == "__main__":  # python -m clgs.bench.field_sample_rows
    import sys

    for r in rows(quick="--quick" in sys.argv):
        print(r)
