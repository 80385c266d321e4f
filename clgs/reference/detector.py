"""Plain NumPy sampling of a detector image, the reference the backprojection kernels are tested
against: bilinear between pixel centres, zero outside the detector."""
from __future__ import annotations

import numpy as np


def bilinear_zero_outside(image: np.ndarray, uf: np.ndarray, vf: np.ndarray) -> np.ndarray:
    """``image`` (V, U) sampled at continuous pixel coordinates ``uf`` (column) and ``vf`` (row),
    any shape alike; each of the four neighbours outside the detector counts as zero."""
    nv, nu = image.shape
    u0, v0 = np.floor(uf).astype(int), np.floor(vf).astype(int)
    fu, fv = uf - u0, vf - v0
    val = np.zeros(np.shape(uf))
    for du, wu in ((0, 1 - fu), (1, fu)):
        for dv, wv in ((0, 1 - fv), (1, fv)):
            iu, iv = u0 + du, v0 + dv
            ok = (iu >= 0) & (iu < nu) & (iv >= 0) & (iv < nv)
            val += np.where(ok, image[np.clip(iv, 0, nv - 1), np.clip(iu, 0, nu - 1)], 0.0) * wu * wv
    return val
