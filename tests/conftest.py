"""Shared test settings: a fixed seed; torch's idle threads told to sleep so PoCL gets the cores."""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before anything imports torch

import clgs  # noqa: E402,F401  (sets the same default for library users)
import numpy as np  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
