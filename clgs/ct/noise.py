"""Simulated X-ray acquisition noise on line-integral projections (the model TIGRE uses, plus
scatter).

For line integrals ``p`` (value x mm):

1. primary intensity ``I = I0 exp(-p / max_p)``, ``max_p`` = the largest line integral unless
   given, so the most attenuating ray keeps ``I0 / e`` counts (TIGRE's normalisation; ``I0`` is
   then the photon count of an unattenuated ray). The noise level is thus relative to the object:
   ``I0`` is not the flat field of a real dose, where a thick object's rays fall far below
   ``I0 / e``;
2. scatter (``scatter`` = scatter-to-primary ratio, SPR): per view, the primary image blurred by
   a wide Gaussian (standard deviation an eighth of the larger detector side, in pixels), scaled
   so that its mean is ``scatter`` times the mean primary. Scatter is smooth and low-frequency,
   as in real scans; it is added to the signal and not corrected, so it biases the line
   integrals low the way uncorrected scatter does;
3. Poisson counts with mean ``I + S``;
4. additive Gaussian electronic noise of standard deviation ``sigma`` counts;
5. counts clipped to at least 1 (a log of zero has no meaning; detectors report a floor);
6. back to line integrals: ``p' = -log(counts / I0) * max_p``.

A seeded NumPy Generator draws everything, so the same ``seed`` gives the same bits.
"""
from __future__ import annotations

import numbers

import numpy as np

from clgs.errors import InputError


def _check(projections, I0, sigma, scatter, max_p):
    p = np.asarray(projections, np.float64)
    if p.ndim != 3 or p.shape[0] == 0:
        raise InputError(f"projections must be (n_views, V, U) with at least one view, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError("projections contain NaN or Inf values; noise cannot be simulated on them")
    if not (np.isfinite(I0) and I0 > 0):
        raise InputError(f"I0 (unattenuated photon count) must be positive, got {I0}")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise InputError(f"sigma (electronic noise, counts) must be >= 0, got {sigma}")
    if not (np.isfinite(scatter) and scatter >= 0):
        raise InputError(f"scatter (scatter-to-primary ratio) must be >= 0, got {scatter}")
    if max_p is None:
        max_p = float(p.max())
        if max_p <= 0:
            max_p = 1.0  # nothing attenuates: any positive scale gives I = I0
    elif not (np.isfinite(max_p) and max_p > 0):
        raise InputError(f"max_p must be positive, got {max_p}")
    return p, float(max_p)


def expected_counts(projections, I0=1e5, scatter=0.0, max_p=None) -> np.ndarray:
    """Mean detector counts ``I + S`` (before Poisson and electronic noise), float64."""
    from scipy.ndimage import gaussian_filter

    p, max_p = _check(projections, I0, 0.0, scatter, max_p)
    primary = I0 * np.exp(-p / max_p)
    if scatter == 0:
        return primary
    width = max(p.shape[1:]) / 8.0
    out = np.empty_like(primary)
    for i, view in enumerate(primary):
        blurred = gaussian_filter(view, sigma=width, mode="nearest")
        mean_b = float(blurred.mean())
        s = blurred * (scatter * float(view.mean()) / mean_b) if mean_b > 0 else 0.0
        out[i] = view + s
    return out


def simulate_counts(projections, I0=1e5, sigma=10.0, scatter=0.0, seed=0, max_p=None):
    """Noisy detector counts (n_views, V, U) float64, clipped to >= 1, and the ``max_p`` used."""
    p, max_p = _check(projections, I0, sigma, scatter, max_p)
    if isinstance(seed, numbers.Integral) and not isinstance(seed, bool) and seed < 0:
        raise InputError(f"seed must be None or a non-negative integer, got {seed}")
    mean = expected_counts(p, I0, scatter, max_p)
    rng = np.random.default_rng(seed)
    counts = rng.poisson(mean).astype(np.float64)
    if sigma > 0:
        counts += rng.normal(0.0, sigma, size=counts.shape)
    np.maximum(counts, 1.0, out=counts)
    return counts, max_p


def add_noise(projections, I0=1e5, sigma=10.0, scatter=0.0, seed=0, max_p=None) -> np.ndarray:
    """Noisy line integrals, same shape as ``projections``, float32 (model in the module docstring).

    ``I0``: photon count of an unattenuated ray, the line integrals divided by ``max_p`` first
    (``I = I0 exp(-p / max_p)``); ``sigma``: electronic noise (counts); ``scatter``:
    scatter-to-primary ratio; ``max_p``: normalising line integral (default: the largest).
    """
    counts, max_p = simulate_counts(projections, I0, sigma, scatter, seed, max_p)
    return (-np.log(counts / I0) * max_p).astype(np.float32)
