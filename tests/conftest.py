"""Shared test settings: a fixed seed, and doubles available for gradient checks."""
import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
