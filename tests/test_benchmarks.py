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


def test_bench_kernels_vectors_times_each_row_three_ways():
    out = _run("kernels", "--n", "600", "--det", "128", "--beam", "cone", "--repeat", "2", "--torch-n", "100",
               "--vectors")
    lines = [l for l in out.splitlines() if "circular / vectors / tilted vectors:" in l]
    assert len(lines) == 2  # affine and exact
    for line in lines:
        assert re.search(r"vectors/circular fwd\+bwd [0-9.]+x \(CPU [0-9.]+x\), tilted/circular [0-9.]+x", line)
    ct = [l for l in out.splitlines() if l.startswith("CT projector")]
    assert len(ct) == 2 and all(re.search(r"vectors/circular [0-9.]+x$", l) for l in ct)


def test_the_tilted_bench_scan_is_the_same_scan_turned():
    import numpy as np

    from clgs.bench.kernels import tilted
    from clgs.geometry import Geometry

    g = Geometry.default(n_views=4, n_detector=32, n_voxel=16)
    t = tilted(g, 5.0, 5.0)
    a, b = g.view_vectors(scene=False), t.view_vectors(scene=False)
    np.testing.assert_array_equal(a[:, :6], b[:, :6])  # source and detector centre stay
    np.testing.assert_allclose(np.linalg.norm(b[:, 6:9], axis=1), np.linalg.norm(a[:, 6:9], axis=1))
    cos_u = np.sum(a[:, 6:9] * b[:, 6:9], 1) / np.sum(a[:, 6:9] ** 2, 1)
    np.testing.assert_allclose(cos_u, np.cos(np.deg2rad(5.0)))  # rolled 5 degrees in the plane
    assert np.all(np.abs(b[:, 11]) < np.abs(a[:, 11]))  # and pitched: v leaves the z axis


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


def test_bench_train_prints_where_an_iteration_goes_and_memory():
    out = _run("train", "--gaussians", "400", "--detector", "32", "--voxels", "16", "--views", "4",
               "--iterations", "3", "--torch-iterations", "0")
    assert "where an iteration goes" in out and "each kernel waited for" in out
    assert re.search(r"OpenCL op Project\s+[0-9.]+", out) and re.search(r"OpenCL op ProjectBackward\s+[0-9.]+", out)
    assert "torch operations (aten)" in out and "of which" in out
    assert re.search(r"peak resident memory of this process: [0-9]+ MiB", out)


def test_bench_train_on_two_devices_prints_the_ratio_table():
    from clgs import runtime

    working = runtime.working_devices()
    specs = [c.index for c in runtime.candidates() if c.ok][:2]
    if len(working) < 2:
        specs = specs * 2  # the same device twice: the table still compares the two runs
    out = _run("train", "--gaussians", "300", "--detector", "32", "--voxels", "16", "--views", "4",
               "--iterations", "2", "--torch-iterations", "0", "--device", specs[0], "--device", specs[1])
    assert out.count("== device: ") == 2
    assert "side by side (same run)" in out and re.search(r"training iteration\s+[0-9.]+\s+[0-9.]+", out)


def test_bench_scaling_prints_both_series_the_fit_and_draws_the_plot(tmp_path):
    plot = tmp_path / "scaling.png"
    out = _run("scaling", "--gaussians", "500", "--gaussians", "1000", "--detectors", "32", "--detectors", "48",
               "--iterations", "1", "--views", "2", "--out", str(plot))
    assert len(re.findall(r"N\s+(500|1000), 256\^2:\s+[0-9.]+ ms / it", out)) == 2
    assert len(re.findall(r"N\s+50000, (32|48)\^2:\s+[0-9.]+ ms / it", out)) == 2
    assert "linear fit over N" in out and plot.is_file() and plot.stat().st_size > 1000


def test_bench_train_refuses_the_shape_only_options_for_r2gs():
    for extra in (["--alternate", "2"], ["--at-iteration", "100"]):
        res = CliRunner().invoke(cli, ["bench", "train", "--gaussians", "300", *extra])
        assert res.exit_code == 2 and "go with --method shape" in res.output


def test_bench_quality_time_runs_both_schedules_and_reads_a_reference_back(tmp_path):
    """Both schedules on a tiny simulated scan: each run's figures, the levels the paper run sets,
    the ratio line; then the paper run read back with --reference (a second process's figures,
    said so) gives the same table for a fast run."""
    from gaussian_scene import six_gaussian_scan

    six_gaussian_scan().save(tmp_path / "scan")
    common = ["--method", "r2gs", "--log-every", "10", "--set", "n_gaussians=200"]
    out = _run("quality-time", str(tmp_path / "scan"), *common, "--paper-iterations", "40", "--fast-iterations",
               "20", "-o", str(tmp_path / "qt"))
    assert re.search(r"paper: 40 of 40 iterations \(ran to its end\), .*3D PSNR [0-9.]+ dB", out)
    assert re.search(r" fast: 20 of 20 iterations", out)
    assert "3D PSNR >= " in out and "(final - 0.1)" in out
    assert re.search(r"fast against paper: [0-9.]+ of its time, [-+][0-9.]+ dB", out)
    for name in ("paper", "fast"):
        assert (tmp_path / "qt" / name / "log.csv").is_file() and (tmp_path / "qt" / name / "run.json").is_file()
    again = _run("quality-time", str(tmp_path / "scan"), *common, "--fast-iterations", "20", "--reference",
                 str(tmp_path / "qt" / "paper"))
    assert "an earlier process" in again and re.search(r" fast: 20 of 20 iterations", again)
    # the fast run is the paper's cut short: the same figures at the same iterations
    import json

    from clgs.fit.training_log import TrainingLog

    paper = TrainingLog.read_csv(tmp_path / "qt" / "paper" / "log.csv").rows
    fast = TrainingLog.read_csv(tmp_path / "qt" / "fast" / "log.csv").rows
    assert json.loads((tmp_path / "qt" / "fast" / "run.json").read_text())["config"]["schedule_iterations"] == 30000
    assert [r["iteration"] for r in fast] == [0, 10, 20]
    assert fast[0]["psnr3d"] == paper[0]["psnr3d"]


def test_bench_iteration_cost_times_a_trained_runs_settings_against_variants(tmp_path):
    """A tiny R2-Gaussian run's checkpoint, timed under its own settings and two variants in
    alternating rounds: one row each, the run's own at 1.00x; a folder without a checkpoint and an
    unknown setting are refused with what to do."""
    from gaussian_scene import six_gaussian_scan

    from clgs.methods.r2gs import reconstruct_r2gs

    scan = six_gaussian_scan()
    scan.save(tmp_path / "scan")
    reconstruct_r2gs(scan, tmp_path / "run", 12, progress=False, n_gaussians=150, init="random", value_scale=60.0,
                     log_every=0, densify_start=2, densify_interval=4, densify_until=8)
    out = _run("iteration-cost", str(tmp_path / "run"), "--scan", str(tmp_path / "scan"), "--variant", "tv_every=2",
               "--variant", "tv_size=4,lambda_dssim=0", "--rounds", "2", "--block", "2")
    assert re.search(r"scene: [0-9]+ Gaussians of .*run \(trained 12 iterations\).*timed from iteration 12 on", out)
    assert re.search(r"the run's settings\s+[0-9.]+\s+1\.00x", out)
    assert re.search(r"tv_every=2\s+[0-9.]+\s+[0-9.]+x", out)
    assert re.search(r"tv_size=4,lambda_dssim=0\s+[0-9.]+\s+[0-9.]+x", out)
    res = CliRunner().invoke(cli, ["bench", "iteration-cost", str(tmp_path / "scan"), "--scan", str(tmp_path / "scan")])
    assert res.exit_code == 2 and "holds no checkpoint.pt" in res.output
    res = CliRunner().invoke(cli, ["bench", "iteration-cost", str(tmp_path / "run"), "--scan", str(tmp_path / "scan"),
                                   "--variant", "tv_evry=2"])
    assert res.exit_code == 2 and "tv_evry" in res.output


def test_bench_quality_time_stops_on_a_signal_and_never_takes_the_stopped_run_for_a_reference(tmp_path,
                                                                                            monkeypatch):
    """SIGTERM during the paper run: its run.json says interrupted, the fast run does not start, the
    command exits 143; that folder is then refused as a --reference."""
    import json
    import os
    import signal

    from gaussian_scene import six_gaussian_scan

    from clgs.fit.trainer import Trainer

    six_gaussian_scan().save(tmp_path / "scan")
    real_step = Trainer.step

    def step(self):
        if self.iteration == 7:
            os.kill(os.getpid(), signal.SIGTERM)
        return real_step(self)

    monkeypatch.setattr(Trainer, "step", step)
    common = ["--method", "r2gs", "--log-every", "10", "--set", "n_gaussians=200"]
    res = CliRunner().invoke(cli, ["bench", "quality-time", str(tmp_path / "scan"), *common, "--paper-iterations",
                                   "40", "--fast-iterations", "20", "-o", str(tmp_path / "qt")])
    assert res.exit_code == 128 + signal.SIGTERM, res.output
    assert "stopped by SIGTERM at iteration 8 of 40" in res.output
    record = json.loads((tmp_path / "qt" / "paper" / "run.json").read_text())
    assert record["interrupted"] and record["iterations"] == 8 and record["stop_signal"] == signal.SIGTERM
    assert not (tmp_path / "qt" / "fast").exists()
    monkeypatch.setattr(Trainer, "step", real_step)
    again = CliRunner().invoke(cli, ["bench", "quality-time", str(tmp_path / "scan"), *common, "--fast-iterations",
                                     "20", "--reference", str(tmp_path / "qt" / "paper")])
    assert again.exit_code == 2 and "stopped by a signal at iteration 8 of 40" in again.output


def test_bench_quality_time_refuses_a_reference_folder_it_did_not_write(tmp_path):
    from gaussian_scene import six_gaussian_scan

    six_gaussian_scan().save(tmp_path / "scan")
    (tmp_path / "ref").mkdir()
    args = ["bench", "quality-time", str(tmp_path / "scan"), "--method", "r2gs", "--reference", str(tmp_path / "ref")]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 2 and "holds no run.json and no log.csv" in res.output
    (tmp_path / "ref" / "run.json").write_text("{")
    (tmp_path / "ref" / "log.csv").write_text("")
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 2 and "run.json is not readable JSON" in res.output
