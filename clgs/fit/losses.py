"""Loss terms of R2-Gaussian (torch): L1 and D-SSIM on projections, TV on a voxelised patch.

The SSIM follows 3DGS / R2-Gaussian: an 11x11 Gaussian window (sigma 1.5), ``C1 = 0.01^2``,
``C2 = 0.03^2`` (projections are in training units of order 1, see ``clgs.methods.r2gs``), zero padding.
The window is separable and applied as two 1D passes: the same filter at a fraction of the cost
of an 11x11 convolution. Against a fixed target (training) the SSIM's backward is written out
(the filter is self-adjoint), a few passes over the image instead of autograd's dozens.

These torch functions are the reference (tests) and the fallback. Training on the OpenCL backend
takes L1 and D-SSIM together from :mod:`clgs.ops.ssim` (three kernel passes for both terms and
their gradient), through :class:`ImageTerms`.
"""
from __future__ import annotations

import weakref

import torch

from clgs.errors import InputError
from clgs.metrics import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, tv_count
from clgs.ops import ssim as ssim_cl
from clgs.ops.ssim import Blur, shift_blur, target_maps
from clgs.ops.ssim import window as window_tensor


def _ssim_terms(a, b, mu_b, bb, wl, c1, c2):
    """The SSIM map's factors (numerator ``a1 a2``, denominator ``b1 b2``) and ``mu_a``."""
    n = a.shape[0]
    maps = Blur.apply(torch.cat([a, a * a, a * b], 0), wl)  # one batched filter pass for the rest
    mu_a, aa, ab = maps[:n], maps[n:2 * n], maps[2 * n:]
    va, vb, cov = aa - mu_a * mu_a, bb - mu_b * mu_b, ab - mu_a * mu_b
    return mu_a, (2 * mu_a * mu_b + c1), (2 * cov + c2), (mu_a * mu_a + mu_b * mu_b + c1), (va + vb + c2)


class _SSIMMap(torch.autograd.Function):
    """The SSIM map of ``a`` against a fixed ``b`` with its chain rule written out: the gradients
    of the three filtered maps come from the factors the forward keeps, and one batched (self-
    adjoint) filter pass carries them back to ``a``; several times fewer passes over the image
    than autograd through the same formula."""

    @staticmethod
    def forward(ctx, a, b, mu_b, bb, wl, c1, c2):
        mu_a, a1, a2, b1, b2 = _ssim_terms(a, b, mu_b, bb, wl, c1, c2)
        num, den = a1 * a2, b1 * b2
        s = num / den
        ctx.save_for_backward(a, b, mu_a, mu_b, a1, a2, b1, b2, den, s)
        ctx.wl = wl
        return s

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gs):
        a, b, mu_a, mu_b, a1, a2, b1, b2, den, s = ctx.saved_tensors
        q = gs / den
        d_a1, d_a2 = q * a2, q * a1  # dS/d(a1 a2) = 1 / den
        d_den = -(q * s)
        d_b1, d_b2 = d_den * b2, d_den * b1
        # a1 = 2 mu_a mu_b + c1, a2 = 2 (ab - mu_a mu_b) + c2, b1 = mu_a^2 + ..., b2 = aa - mu_a^2 + ...
        g_mu = 2 * (mu_b * (d_a1 - d_a2) + mu_a * (d_b1 - d_b2))
        g = shift_blur(torch.cat([g_mu, d_b2, 2 * d_a2], 0), ctx.wl)
        n = a.shape[0]
        return g[:n] + 2 * a * g[n:2 * n] + b * g[2 * n:], None, None, None, None, None, None


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA,
         c1: float = SSIM_C1, c2: float = SSIM_C2, b_maps=None) -> torch.Tensor:
    """Mean SSIM of images ``a``, ``b`` shaped (H, W) or (B, H, W); ``b_maps`` = ``target_maps(b)``
    when ``b`` is fixed and its maps are cached."""
    if a.shape != b.shape:
        raise InputError(f"ssim: shapes differ, {tuple(a.shape)} vs {tuple(b.shape)}")
    a = a.reshape(-1, 1, *a.shape[-2:])
    b = b.reshape(-1, 1, *b.shape[-2:])
    w = window_tensor(window, sigma, a.dtype)
    if b_maps is None:
        mu_b, bb = target_maps(b, window, sigma)
    else:
        mu_b, bb = b_maps
    wl = w.tolist()
    if torch.is_grad_enabled() and not any(t.requires_grad for t in (b, mu_b, bb)):
        return _SSIMMap.apply(a, b, mu_b, bb, wl, c1, c2).mean()  # the usual case: b is measured data
    _, a1, a2, b1, b2 = _ssim_terms(a, b, mu_b, bb, wl, c1, c2)
    return ((a1 * a2) / (b1 * b2)).mean()


def dssim(a: torch.Tensor, b: torch.Tensor, b_maps=None) -> torch.Tensor:
    """D-SSIM = 1 - SSIM (R2-Gaussian weighs it 0.25)."""
    return 1.0 - ssim(a, b, b_maps=b_maps)


def l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()


class ImageTerms:
    """L1 and D-SSIM of a training context's render against its measured view, as two loss-term
    functions (``self.l1``, ``self.dssim``) that share their work within an iteration.

    On the OpenCL backend (CPU float32/float64 renders) both terms come from one call of
    :func:`clgs.ops.ssim.l1_dssim`: three kernel passes give both values and, on backward, the
    gradient of whatever weighted sum the trainer formed; the result is kept per context (weakly:
    it goes with the context) so the second term costs nothing. Elsewhere (the torch backend, or
    a render the kernels do not take) they are :func:`l1` and :func:`dssim`. The target's filtered
    maps are computed once per view in either case.

    ``dssim=False`` (a D-SSIM weight of 0): ``l1`` is the plain L1 and no SSIM pass runs at all
    (``dssim`` still works if called, on its own)."""

    def __init__(self, dssim: bool = True):
        self.fused = bool(dssim)
        self._maps: dict = {}  # (view, dtype, shape) -> (mu_b, bb), torch path
        self._targets: dict = {}  # (view, dtype, shape) -> clgs.ops.ssim.SSIMTarget, OpenCL path
        self._results = weakref.WeakKeyDictionary()  # context -> (l1, dssim), OpenCL path

    @staticmethod
    def _use_cl(ctx, render) -> bool:
        return (getattr(getattr(ctx.trainer, "backend", None), "name", None) == "cl" and render.device.type == "cpu"
                and render.dtype in (torch.float32, torch.float64) and render.dim() in (2, 3)
                and not ctx.target.requires_grad)

    def _target_maps(self, ctx):
        key = (ctx.view, ctx.target.dtype, tuple(ctx.target.shape))
        maps = self._maps.get(key)
        if maps is None:
            with torch.no_grad():
                maps = self._maps[key] = target_maps(ctx.target)
        return maps

    def _both(self, ctx):
        out = self._results.get(ctx)
        if out is None:
            render = ctx.render
            key = (ctx.view, render.dtype, tuple(render.shape))  # coarse-to-fine renders change size
            target = self._targets.get(key)
            if target is None:  # b and its maps, padded for the kernels (not kept twice)
                target = self._targets[key] = ssim_cl.SSIMTarget(ctx.target.detach().to(render.dtype))
            out = self._results[ctx] = ssim_cl.l1_dssim(render, target)
        return out

    def l1(self, ctx) -> torch.Tensor:
        if self.fused and self._use_cl(ctx, ctx.render):
            return self._both(ctx)[0]
        return l1(ctx.render, ctx.target)

    def dssim(self, ctx) -> torch.Tensor:
        if self._use_cl(ctx, ctx.render):
            return self._both(ctx)[1]
        return dssim(ctx.render, ctx.target, b_maps=self._target_maps(ctx))


def tv3d(vol: torch.Tensor) -> torch.Tensor:
    """Anisotropic total variation of a (Z, Y, X) block: the mean absolute difference between
    neighbours, over all the differences of the three axes together (R2-Gaussian's definition;
    the sum of the three per-axis means would weigh TV 3x as much on a cube)."""
    if vol.dim() != 3:
        raise InputError(f"tv3d needs a (Z, Y, X) block, got shape {tuple(vol.shape)}")
    count = tv_count(vol.shape)
    out = vol.new_zeros(())
    if count == 0:
        return out
    for axis in range(3):
        if vol.shape[axis] > 1:
            out = out + torch.diff(vol, dim=axis).abs().sum()
    return out / count


def random_block(grid, size: int, generator: torch.Generator, subvoxel: bool = False):
    """A random ``size^3`` sub-grid of ``grid`` (clipped to the grid), drawn with ``generator``.

    ``subvoxel``: the block's samples are also shifted by a random fraction of a voxel along each
    axis (staying inside the grid), so that over the iterations they do not always sit on the
    voxel centres where the volume is evaluated. A TV patch on the fixed lattice lets training
    lower the TV by moving mass between lattice points, which the projections still see but the
    evaluated volume loses (thin bright structures came out at half their value)."""
    if not subvoxel:
        size_zyx = [min(int(size), n) for n in grid.shape]
        start = [int(torch.randint(0, n - s + 1, (1,), generator=generator)) for n, s in zip(grid.shape, size_zyx)]
        return grid.block(start, size_zyx)
    size_zyx = [max(1, min(int(size), n - 1)) for n in grid.shape]
    start = [int(torch.randint(0, max(n - s, 1), (1,), generator=generator)) for n, s in zip(grid.shape, size_zyx)]
    frac = torch.rand(3, generator=generator, dtype=torch.float64).tolist()  # x, y, z
    frac = [f if n > 1 else 0.0 for f, n in zip(frac, grid.shape[::-1])]
    b = grid.block(start, size_zyx)
    return type(b)(b.shape, tuple(o + f * d for o, f, d in zip(b.origin, frac, b.spacing)), b.spacing)
