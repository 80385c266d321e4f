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


def test_bench_train_prints_rates_and_the_breakdown():
    out = _run("train", "--gaussians", "400", "--detector", "32", "--voxels", "16", "--views", "4",
               "--iterations", "3", "--torch-iterations", "1")
    assert re.search(r"OpenCL: [0-9.]+ it/s", out)
    assert "speed-up over torch" in out and "projection kernels" in out
