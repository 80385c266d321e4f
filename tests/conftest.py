"""Shared test settings: a fixed seed; torch's idle threads told to sleep so PoCL gets the cores."""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before anything imports torch

import clgs  # noqa: E402,F401  (sets the same default for library users)
import numpy as np  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def one_torch_thread():
    """Small tensors: one torch thread is faster (and steadier on a shared machine)."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
