"""How good a population's shape space is: compactness, generalisation and specificity of a PCA.

These are the usual figures of a statistical shape model (Davies et al.; Styner et al.). Two
uses: :func:`shape_space_figures` on surfaces in vertex correspondence (a PCA of the vertex
coordinates, needs no registration: ``clgs <anatomy> info`` without a built model), and
:func:`field_space_figures` on the model's own velocity fields, measured at the template's
surface points (what the model builder prints, stores and chooses its mode count from).

* compactness(M): the share of the population's variance that the first M modes hold;
* generalisation(M): leave one subject out, build the PCA from the others, reconstruct the left
  out member from its first M modes; the mean point distance (mm), averaged over subjects: how
  far a new member of the population lies outside an M-mode span;
* specificity(M): random members of the M-mode model (coefficients ~ N(0, 1) times each mode's
  standard deviation), each one's mean point distance (mm) to its nearest subject, averaged: how
  far from real shapes the model wanders.

The PCA runs on the Gram matrix of the full rows (N x N: few subjects, many coordinates); the
distances are taken on ``measure(rows)``, a linear map (e.g. a field sampled at surface points),
so a leave-one-out PCA of a large field costs no more than one of a small surface.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from clgs.errors import InputError


def _mean_point_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean distance (mm) between corresponding points of flattened point sets a (..., P*3), b."""
    d = (a - b).reshape(*np.broadcast_shapes(a.shape, b.shape)[:-1], -1, 3)
    return np.linalg.norm(d, axis=-1).mean(-1)


def _gram_pca(gram: np.ndarray, measured: np.ndarray):
    """PCA of rows whose Gram matrix is ``gram`` (n, n), in measured space: (mean (P3,), modes
    (K, P3) = the full-space orthonormal modes measured, standard deviations (K,), u (n, K) and
    singular values (K,) for projecting further rows)."""
    n = len(gram)
    h = np.eye(n) - 1.0 / n
    w, u = np.linalg.eigh(h @ gram @ h)
    order = np.argsort(w)[::-1][:max(n - 1, 1)]
    w, u = np.clip(w[order], 0.0, None), u[:, order]
    s = np.sqrt(w)
    safe = np.where(s > 0, s, 1.0)
    modes = (u.T @ (measured - measured.mean(0))) / safe[:, None]
    return measured.mean(0), modes, s / np.sqrt(max(n - 1, 1)), u, safe


def field_space_figures(rows, measure: Callable | None = None, max_modes: int | None = None,
                        n_samples: int = 200, seed: int = 0) -> dict:
    """{"modes": [1..K], "compactness", "generalisation_mm", "specificity_mm": one per mode count}
    of a PCA of ``rows`` (N, D), the distances measured on ``measure(rows)`` ((k, D) -> (k, P*3)
    points in mm, linear; None: the rows themselves are points); K = ``max_modes`` or N - 2
    (leave-one-out leaves N - 1 rows, whose PCA has N - 2 modes)."""
    x = np.asarray(rows, np.float64)
    if x.ndim != 2:
        raise InputError(f"rows must be (N, D), got {x.shape}")
    n = x.shape[0]
    if n < 3:
        raise InputError(f"shape-space figures need at least 3 subjects, got {n}")
    if not np.isfinite(x).all():
        raise InputError("the population's fields or surfaces contain NaN or Inf")
    x = x - x.mean(0)  # a common offset changes nothing and keeps the Gram matrix well scaled
    y = x if measure is None else np.asarray(measure(x), np.float64)
    if y.ndim != 2 or len(y) != n or y.shape[1] % 3:
        raise InputError(f"measure must map (N, D) rows to (N, P*3) points, got {y.shape}")
    gram = x @ x.T
    k = max(min(int(max_modes or n - 2), n - 2), 1)
    mean, modes, sd, _, _ = _gram_pca(gram, y)
    var = sd ** 2
    total = var.sum()
    compact = np.cumsum(var)[:k] / total if total > 0 else np.ones(k)
    general = np.zeros(k)
    for i in range(n):
        o = np.delete(np.arange(n), i)
        m, v, _, u, s = _gram_pca(gram[np.ix_(o, o)], y[o])
        g = gram[np.ix_(o, o)]
        # (x_j - mean_o) . (x_i - mean_o) for j in o, from the Gram matrix alone
        d = gram[o, i] - gram[o, i].mean() - g.mean(1) + g.mean()
        coef = (u.T @ (d - d.mean()))[:k] / s[:k]
        resid = y[i] - m
        for j in range(1, k + 1):
            general[j - 1] += _mean_point_distance(resid - coef[:j] @ v[:j], np.zeros_like(resid)) / n
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n_samples, k))
    spec = np.zeros(k)
    for j in range(1, k + 1):
        samples = mean + (z[:, :j] * sd[:j]) @ modes[:j]
        nearest = np.min([_mean_point_distance(samples, yi) for yi in y], axis=0)  # per sample
        spec[j - 1] = nearest.mean()
    return {"modes": list(range(1, k + 1)), "compactness": [float(c) for c in compact],
            "generalisation_mm": [float(g) for g in general], "specificity_mm": [float(s) for s in spec]}


def shape_space_figures(surfaces, max_modes: int | None = None, n_samples: int = 200, seed: int = 0) -> dict:
    """:func:`field_space_figures` of ``surfaces`` (N, V, 3) mm in vertex correspondence (a PCA
    of the vertex coordinates, distances between corresponding vertices)."""
    x = np.asarray(surfaces, np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise InputError(f"surfaces must be (N, V, 3) in vertex correspondence, got {x.shape}")
    if x.shape[0] < 3:
        raise InputError(f"shape-space figures need at least 3 surfaces, got {x.shape[0]}")
    if not np.isfinite(x).all():
        raise InputError("surfaces contain NaN or Inf")
    return field_space_figures(x.reshape(len(x), -1), None, max_modes, n_samples, seed)
