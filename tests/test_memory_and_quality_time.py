"""The memory a large scene needs stays within a stated bound; time to quality from the log."""
import json
import subprocess
import sys

import pytest

from clgs.fit.training_log import TrainingLog

#: a 100k-Gaussian R2-Gaussian-mode run on a 512^2 detector stays under this (docs/benchmarks.md)
MEMORY_BOUND_MIB = 2048

CHECK = r"""
import json
from clgs.bench.train import peak_memory_mib, r2gs_trainer, synthetic_scene
geo, scan, gaussians = synthetic_scene(100_000, 512, 128, 4, "cone", 0)
trainer = r2gs_trainer(scan, gaussians, "cl", 0)
for _ in range(3):
    trainer.step()
print(json.dumps({"peak_mib": peak_memory_mib(), "n": trainer.n_gaussians}))
"""


def test_100k_gaussians_on_a_512_detector_stay_within_the_memory_bound():
    res = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["n"] == 100_000
    assert 200 < out["peak_mib"] < MEMORY_BOUND_MIB, out


def test_time_to_quality_interpolates_between_the_rows_around_each_level():
    log = TrainingLog([
        {"iteration": 0, "seconds": 0.0, "wall": 0.5, "psnr3d": 24.6},
        {"iteration": 100, "seconds": 5.0, "wall": 6.0, "psnr3d": 26.2},
        {"iteration": 200, "seconds": 10.0, "wall": 11.5, "psnr3d": 25.9},
        {"iteration": 300, "seconds": 15.0, "wall": 17.0, "psnr3d": 27.0},
    ])
    got = log.time_to_quality()
    assert [g[0] for g in got] == [25.0, 26.0, 27.0]
    # 25 and 26 dB both lie between the first two rows: each its own time, in proportion
    assert got[0][1:] == pytest.approx((0.4 / 1.6 * 5.0, 0.5 + 0.4 / 1.6 * 5.5))
    assert got[1][1:] == pytest.approx((1.4 / 1.6 * 5.0, 0.5 + 1.4 / 1.6 * 5.5))
    # 27 dB: first reached at the last row (the dip at 200 does not count as reaching it earlier)
    assert got[2][1:] == pytest.approx((15.0, 17.0))
    assert "27 dB at 15.0 / 17.0 s" in log.summary() and "linear between" in log.summary()
    assert TrainingLog([{"seconds": 0.0, "psnr3d": 20.0}]).time_to_quality() == []
