"""The benchmark commands run end to end on tiny cases and print their figures (no timing is
asserted: speed is measured by running them, never by tests)."""
from __future__ import annotations

import re

from click.testing import CliRunner

from clgs.cli import main as cli


def _run(*args):
    res = CliRunner().invoke(cli, ["bench", *args], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res.output


def test_bench_kernels_prints_its_table_and_the_fastest_calls():
    out = _run("kernels", "--n", "800", "--det", "128", "--beam", "cone", "--repeat", "2", "--torch-n", "100",
               "--fastest")
    rows = [l for l in out.splitlines() if re.match(r"\s+800\s+128\^2\s+cone\s+(affine|exact) \|", l)]
    assert len(rows) == 2
    assert out.count("fastest of 2 calls: fwd") == 2
    assert "exp ceiling" in out and "Geval/s" in out
    assert re.search(r"machine during the run: load average [0-9.]+ on [0-9]+ cores; [0-9]+% of the CPU time", out)


def test_bench_train_prints_rates_and_the_breakdown():
    out = _run("train", "--gaussians", "400", "--detector", "32", "--voxels", "16", "--views", "4",
               "--iterations", "3", "--torch-iterations", "1")
    assert re.search(r"OpenCL: [0-9.]+ it/s", out)
    assert "speed-up over torch" in out and "projection kernels" in out
    assert "machine during the run" in out


def test_stage_timing_waits_on_the_profiling_queue():
    """``--stages`` runs the projector on a profiling queue of its own: the call must read its
    results back on that queue too, so every call's wall time holds its kernels' device time
    (a read-back on another queue returned before the kernels ended: negative "outside" times)."""
    import numpy as np

    from clgs.bench.kernels import _scene, _stages
    from clgs.geometry import Geometry
    from clgs.ops.projector import GaussianProjector
    from clgs.ops.voxelizer import cov_prec

    geo = Geometry.default(n_views=4, mode="cone", n_detector=128, n_voxel=32)
    m, s, q, r = _scene(3000)
    proj = GaussianProjector()
    queue = proj.queue
    ms, launches, outside = _stages(proj, m, cov_prec(s, q)[0], r, geo, "affine", 3)
    assert launches == {"fwd": 2, "bwd": 1}
    assert ms["fwd"]["render"] > 0 and ms["bwd"]["backward"] > 0
    assert outside["fwd"] >= 0 and outside["bwd"] >= 0
    assert proj.queue is queue and proj.io.queue is queue
    # the operator's buffers follow whatever queue it runs on
    import pyopencl as cl

    proj.queue = cl.CommandQueue(proj.ctx)
    assert proj.io.queue is proj.queue
    out = proj.forward(m.numpy(), cov_prec(s, q)[0].numpy(), r.numpy(), geo, [0], "affine")
    assert np.isfinite(out).all() and out.max() > 0


def test_deformation_rows_compare_both_paths():
    import math

    from clgs.bench import field_sample_rows

    rows = field_sample_rows.rows(quick=True)
    assert [r["case"] for r in rows] == ["exp(v) forward", "exp(v) forward+backward",
                                         "field at 35k points forward+backward"]
    assert all(r["ms"] > 0 and r["ref_ms"] > 0 and math.isclose(r["speedup"], r["ref_ms"] / r["ms"]) for r in rows)
