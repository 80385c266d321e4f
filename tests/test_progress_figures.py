"""The bar's figures are the final table's: same quantities, same names, same last values; and the
expected run time changes nothing in the run."""
import json
import re

import numpy as np
import pytest
from sphere_scan import sphere_scan

from clgs import metrics, progress
from clgs.fit import estimate
from clgs.fit.training_log import RATE, fmt_rate

N = 16


@pytest.fixture(scope="module")
def scan():
    return sphere_scan(N, 6, 24, 64.0, 25)


def _run(scan, **kw):
    from clgs import reconstruct_r2gs

    return reconstruct_r2gs(scan, iterations=24, n_gaussians=300, log_every=10, seed=3, **kw)


def test_the_bar_ends_on_the_figures_of_the_final_table(scan, monkeypatch, capsys):
    monkeypatch.setenv("CLGS_PROGRESS_SECONDS", "1000")  # a log: the first and the last line
    with progress.listen() as events:
        res = _run(scan, progress=True)
    final = [e for e in events if e["event"] == "figures" and e["desc"] == "train"][-1]
    assert final["final"]
    figures = final["figures"]
    last = res.log.rows[-1]
    # the last row of the log (the summary's "last" line) under the same names
    assert last["iteration"] == 24
    for k in ("loss", "n_gaussians", "proj_psnr", "psnr3d", "ssim3d"):
        assert figures[k] == last[k], k
    # 3D PSNR / SSIM of the volume returned, as the final report measures it
    truth_figures = metrics.volume_figures(res.volume, scan.truth)
    assert figures["psnr3d"] == pytest.approx(truth_figures["psnr3d"], rel=1e-6)
    assert figures["ssim3d"] == pytest.approx(truth_figures["ssim3d"], rel=1e-6)
    # it/s: training time as the summary counts it, not the wall-clock rate
    said = re.search(r"(\d+) iterations in [\d.]+ s of training: ([\d.]+) it/s", res.summary)
    assert said and fmt_rate(figures[RATE]) == said.group(2)
    assert figures[RATE] == pytest.approx(24 / (last["seconds"] - res.log.rows[0]["seconds"]))
    # and the bar's last line shows exactly those, with the same names
    line = [x for x in capsys.readouterr().err.splitlines() if x.startswith("train:")][-1]
    assert f"psnr3d={figures['psnr3d']:.4g}" in line and f"it/s={said.group(2)}" in line, line
    assert "it/s," not in line.replace(f"it/s={said.group(2)}", "")  # no second, wall-clock rate


def test_the_estimate_changes_nothing_in_the_run(scan, monkeypatch, capsys):
    monkeypatch.setattr(estimate, "MIN_SECONDS", 0.0)  # print it even for this tiny run
    with progress.listen() as events:
        told = _run(scan, progress=True)
    notes = [e["text"] for e in events if e["event"] == "note"]
    assert len(notes) == 1 and notes[0].startswith("expected run time: about "), notes
    assert "--set iterations=N" in notes[0] and "expected run time" in capsys.readouterr().err
    assert told.trainer.expected is not None and told.trainer.expected.iterations == 24 - 6
    quiet = _run(scan, progress=False)
    assert quiet.trainer.expected is None
    assert np.array_equal(told.volume, quiet.volume)
    for k in told.gaussians:
        assert np.array_equal(told.gaussians[k], quiet.gaussians[k]), k
    strip = [{k: v for k, v in r.items() if k not in ("seconds", "wall")} for r in told.log.rows]
    assert strip == [{k: v for k, v in r.items() if k not in ("seconds", "wall")} for r in quiet.log.rows]


def test_no_progress_silences_the_bar_and_every_phase_line(scan, tmp_path):
    from cli_helpers import run

    folder = tmp_path / "scan"
    scan.save(folder)
    args = ["reconstruct", folder, "--method", "r2gs", "--iterations", 8, "--gaussians", 200]
    with progress.listen() as events:
        shown = run(*args, "-o", tmp_path / "a").output
    assert "FDK of 6 views on a 16x16x16 grid ..." in shown and "drawing the slices" in shown
    assert "train: 8/8 it (100%)" in shown
    # the bar's last figures are the report's (and the line printed at the end)
    final = [e["figures"] for e in events if e["event"] == "figures" and e["final"]][-1]
    report = json.loads((tmp_path / "a" / "report.json").read_text())
    assert final["psnr3d"] == pytest.approx(report["metrics"]["psnr3d"], rel=1e-6)
    assert final["ssim3d"] == pytest.approx(report["metrics"]["ssim3d"], rel=1e-6)
    assert final[RATE] == pytest.approx(8 / round(report["info"]["training_seconds"], 4))  # the log keeps 4 decimals
    assert f"PSNR {report['metrics']['psnr3d']:.4f} dB" in shown
    quiet = run(*args, "--no-progress", "-o", tmp_path / "b").output
    assert " ..." not in quiet and "train:" not in quiet and "drawing" not in quiet, quiet
