"""The README's comparison script runs end to end (tiny settings) and honours ``--set``."""
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _compare(tmp_path, *extra):
    out = tmp_path / "cmp"
    cmd = [sys.executable, str(EXAMPLES / "compare_methods.py"), "--views", "8", "--iterations", "30",
           "--log-every", "15", "--sart-iterations", "2", "--out", str(out), *extra]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=EXAMPLES, timeout=600)
    return r, out


@pytest.mark.slow
def test_compare_methods_writes_curves_and_summary_with_settings(tmp_path):
    r, out = _compare(tmp_path, "--set", "n_gaussians=3000", "--set", "grad_threshold=3e-5")
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"] == {"n_gaussians": 3000, "grad_threshold": 3e-5}
    assert summary["iterations"] == 30
    for key in ("fdk_psnr", "sart_psnr", "r2gs_psnr"):
        assert math.isfinite(summary[key]) and summary[key] > 10, (key, summary[key])
    assert summary["r2gs_psnr_at_10k"] is None  # the run never reached 10k iterations
    config = json.loads((out / "r2gs" / "config.json").read_text())
    assert config["grad_threshold"] == 3e-5 and config["n_gaussians"] == 3000
    assert (out / "curves.png").stat().st_size > 1000


def test_compare_methods_refuses_a_malformed_setting(tmp_path):
    r, out = _compare(tmp_path, "--set", "grad_threshold")
    assert r.returncode != 0
    assert "KEY=VALUE" in r.stderr
    assert not (out / "summary.json").exists()
