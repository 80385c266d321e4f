"""Loss terms of R2-Gaussian (torch): L1 and D-SSIM on projections, TV on a voxelised patch.

The SSIM follows 3DGS / R2-Gaussian: an 11x11 Gaussian window (sigma 1.5), ``C1 = 0.01^2``,
``C2 = 0.03^2`` (projections are in training units of order 1, see ``clgs.r2gs``), zero padding.
The window is separable and applied as two 1D passes: the same filter at a fraction of the cost
of an 11x11 convolution.
"""
from __future__ import annotations

import torch

_windows: dict = {}


def _window(size: int, sigma: float, dtype) -> torch.Tensor:
    key = (size, sigma, dtype)
    w = _windows.get(key)
    if w is None:
        x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
        g = torch.exp(-(x * x) / (2 * sigma * sigma))
        w = _windows[key] = (g / g.sum()).to(dtype)
    return w


def _band(n: int, w: torch.Tensor) -> torch.Tensor:
    """(n, n) matrix applying the 1D filter ``w`` with zero padding: ``(B x)[i] = sum_k w[k] x[i+k-r]``."""
    key = ("band", n, w.numel(), w.dtype, tuple(w.tolist()))
    m = _windows.get(key)
    if m is None:
        r = w.numel() // 2
        i = torch.arange(n)
        off = i[None, :] - i[:, None] + r  # column - row + r
        ok = (off >= 0) & (off < w.numel())
        m = _windows[key] = torch.where(ok, w[off.clamp(0, w.numel() - 1)], torch.zeros((), dtype=w.dtype))
    return m


def _blur(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (B, 1, H, W) with zero padding ('same' size).

    Written as two products with banded matrices, ``Bv @ x @ Bu^T``: on CPUs these run at matrix-
    multiply speed forward and backward, where a single-channel convolution with a thin kernel (or
    shifted slices, whose backward allocates a full image per tap) is several times slower."""
    h, wd = x.shape[-2:]
    return _band(h, w) @ x @ _band(wd, w).t()


def target_maps(b: torch.Tensor, window: int = 11, sigma: float = 1.5):
    """The blurred mean and second moment of a fixed image ``b`` ((H, W) or (B, H, W)): computed
    once per measured projection, they save two of SSIM's five filter passes every iteration."""
    b = b.reshape(-1, 1, *b.shape[-2:])
    maps = _blur(torch.cat([b, b * b], 0), _window(window, sigma, b.dtype))
    n = b.shape[0]
    return maps[:n], maps[n:]


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5,
         c1: float = 0.01 ** 2, c2: float = 0.03 ** 2, b_maps=None) -> torch.Tensor:
    """Mean SSIM of images ``a``, ``b`` shaped (H, W) or (B, H, W); ``b_maps`` = ``target_maps(b)``
    when ``b`` is fixed and its maps are cached."""
    if a.shape != b.shape:
        raise ValueError(f"ssim: shapes differ, {tuple(a.shape)} vs {tuple(b.shape)}")
    a = a.reshape(-1, 1, *a.shape[-2:])
    b = b.reshape(-1, 1, *b.shape[-2:])
    w = _window(window, sigma, a.dtype)
    n = a.shape[0]
    if b_maps is None:
        mu_b, bb = target_maps(b, window, sigma)
    else:
        mu_b, bb = b_maps
    maps = _blur(torch.cat([a, a * a, a * b], 0), w)  # one batched filter pass for the rest
    mu_a, aa, ab = maps[:n], maps[n:2 * n], maps[2 * n:]
    va, vb, cov = aa - mu_a * mu_a, bb - mu_b * mu_b, ab - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a * mu_a + mu_b * mu_b + c1) * (va + vb + c2))
    return s.mean()


def dssim(a: torch.Tensor, b: torch.Tensor, b_maps=None) -> torch.Tensor:
    """D-SSIM = 1 - SSIM (R2-Gaussian weighs it 0.25)."""
    return 1.0 - ssim(a, b, b_maps=b_maps)


def l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()


def tv3d(vol: torch.Tensor) -> torch.Tensor:
    """Anisotropic total variation of a (Z, Y, X) block: the mean absolute difference between
    neighbours, summed over the three axes."""
    if vol.dim() != 3:
        raise ValueError(f"tv3d needs a (Z, Y, X) block, got shape {tuple(vol.shape)}")
    out = vol.new_zeros(())
    for axis in range(3):
        if vol.shape[axis] > 1:
            out = out + torch.diff(vol, dim=axis).abs().mean()
    return out


def random_block(grid, size: int, generator: torch.Generator):
    """A random ``size^3`` sub-grid of ``grid`` (clipped to the grid), drawn with ``generator``."""
    size_zyx = [min(int(size), n) for n in grid.shape]
    start = [int(torch.randint(0, n - s + 1, (1,), generator=generator)) for n, s in zip(grid.shape, size_zyx)]
    return grid.block(start, size_zyx)
