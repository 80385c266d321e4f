"""How good a population's shape space is, from its surfaces alone: compactness, generalisation
and specificity of a PCA of the vertex coordinates (surfaces in vertex correspondence).

These are the usual figures of a statistical shape model (Davies et al.; Styner et al.), at the
surface level, so they need no registration: the velocity model of :mod:`clgs.shape.model` is
built from the same surfaces, and its mode count (3 for the femur) is read against them.

* compactness(M): the share of the population's variance that the first M modes hold;
* generalisation(M): leave one subject out, build the PCA from the others, reconstruct the left
  out surface from its first M modes; the mean vertex distance (mm), averaged over subjects: how
  far a new member of the population lies outside an M-mode span;
* specificity(M): random shapes from the M-mode model (coefficients ~ N(0, 1) times each mode's
  standard deviation), each one's mean vertex distance (mm) to its nearest subject, averaged: how
  far from real shapes the model wanders.
"""
from __future__ import annotations

import numpy as np

from clgs.errors import InputError


def _pca(x: np.ndarray):
    """(mean (D,), modes (K, D) orthonormal, standard deviations (K,)) of rows x (N, D)."""
    mean = x.mean(0)
    xc = x - mean
    w, u = np.linalg.eigh(xc @ xc.T)  # N x N: few subjects, many coordinates
    order = np.argsort(w)[::-1][:max(len(x) - 1, 1)]
    w, u = np.clip(w[order], 0.0, None), u[:, order]
    s = np.sqrt(w)
    vt = (u.T @ xc) / np.where(s > 0, s, 1.0)[:, None]
    return mean, vt, s / np.sqrt(max(len(x) - 1, 1))


def _mean_vertex_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean distance (mm) between corresponding vertices of flattened surfaces a (..., V*3), b."""
    d = (a - b).reshape(*np.broadcast_shapes(a.shape, b.shape)[:-1], -1, 3)
    return np.linalg.norm(d, axis=-1).mean(-1)


def shape_space_figures(surfaces, max_modes: int | None = None, n_samples: int = 200, seed: int = 0) -> dict:
    """{"modes": [1..K], "compactness": [...], "generalisation_mm": [...], "specificity_mm": [...]}
    of ``surfaces`` (N, V, 3) mm in vertex correspondence (see the module doc); K = ``max_modes``
    or N - 2 (leave-one-out leaves N - 1 subjects, whose PCA has N - 2 modes)."""
    x = np.asarray(surfaces, np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise InputError(f"surfaces must be (N, V, 3) in vertex correspondence, got {x.shape}")
    n = x.shape[0]
    if n < 3:
        raise InputError(f"shape-space figures need at least 3 surfaces, got {n}")
    if not np.isfinite(x).all():
        raise InputError("surfaces contain NaN or Inf")
    x = x.reshape(n, -1)
    k = min(int(max_modes or n - 2), n - 2)
    mean, modes, sd = _pca(x)
    var = sd ** 2
    compact = np.cumsum(var)[:k] / var.sum()
    general = np.zeros(k)
    for i in range(n):
        m, v, _ = _pca(np.delete(x, i, 0))
        coef = v[:k] @ (x[i] - m)
        for j in range(1, k + 1):
            general[j - 1] += _mean_vertex_distance(m + coef[:j] @ v[:j], x[i]) / n
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n_samples, k))
    spec = np.zeros(k)
    for j in range(1, k + 1):
        samples = mean + (z[:, :j] * sd[:j]) @ modes[:j]
        nearest = np.min([_mean_vertex_distance(samples, xi) for xi in x], axis=0)  # per sample
        spec[j - 1] = nearest.mean()
    return {"modes": list(range(1, k + 1)), "compactness": compact.tolist(), "generalisation_mm": general.tolist(),
            "specificity_mm": spec.tolist()}
