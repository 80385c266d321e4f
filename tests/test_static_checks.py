"""The static checks pass: ruff over the code and the tests (the rules of pyproject.toml's
[tool.ruff]), and mypy over the typed layers (clgs.runtime, clgs.ops, clgs.methods; the packages
and settings of [tool.mypy]). Each is skipped, saying so, where its tool is not installed."""
from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(cmd: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)


def test_ruff_finds_nothing():
    if importlib.util.find_spec("ruff") is not None:
        cmd = [sys.executable, "-m", "ruff"]
    elif shutil.which("ruff"):
        cmd = [shutil.which("ruff")]
    else:
        pytest.skip("ruff is not installed (pip install -e '.[test]')")
    r = _run([*cmd, "check", "--no-cache", "clgs", "tests", "examples", "anatomies"])
    assert r.returncode == 0, r.stdout + r.stderr


def test_mypy_finds_nothing_in_runtime_ops_and_methods():
    if importlib.util.find_spec("mypy") is None:
        pytest.skip("mypy is not installed (pip install -e '.[test]')")
    # the packages and the cache folder (.mypy_cache, reused between runs) come from pyproject.toml
    r = _run([sys.executable, "-m", "mypy"])
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Success" in r.stdout
