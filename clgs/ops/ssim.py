"""L1 and D-SSIM of rendered projections against fixed (measured) targets, on OpenCL.

The training loss ``lambda_l1 * mean|a - b| + lambda_dssim * (1 - mean SSIM(a, b))`` and its
gradient with respect to the render ``a``, in three kernel passes (``cl/ssim.cl``) instead of the
few dozen passes over the image that the torch version (:mod:`clgs.fit.losses`, the reference) makes.
The SSIM is exactly :func:`clgs.fit.losses.ssim`'s: an 11-tap Gaussian window (sigma 1.5) applied as
two 1D passes with zero padding, ``C1 = 0.01^2``, ``C2 = 0.03^2``; the target's blurred mean and
second moment are computed once per target (:class:`SSIMTarget`, one per training view).

From Python::

    op = ImageLoss()                       # or default_image_loss()
    target = op.target(b)                  # b (H, W) or (B, H, W), fixed; cache it per view
    l1, dssim = l1_dssim(a, target)        # a like b, requires_grad; two scalar tensors
    (l1 + 0.25 * dssim).backward()         # a.grad

Same input, same bits. The three passes, their layout and their cost: docs/kernels.md.

Non-finite renders: NaN or Inf in ``a`` propagate to the terms (as in torch), and the trainer
stops with a ``FloatingPointError`` naming the iteration and view when the loss is not finite.
"""
from __future__ import annotations

import numpy as np
import torch

from clgs.errors import ClgsError, InputError
from clgs.metrics import SSIM_C1 as C1
from clgs.metrics import SSIM_C2 as C2
from clgs.metrics import SSIM_SIGMA as SIGMA
from clgs.metrics import SSIM_WINDOW as WINDOW
from clgs.metrics import gaussian_window
from clgs.runtime import Operator, real_name, shared

# ------------------------------------------------------------ the filter, in torch (targets, fallback)
_windows: dict = {}  # (size, sigma, dtype) -> window


def window(size: int, sigma: float, dtype) -> torch.Tensor:
    """The normalised 1D Gaussian window of :func:`clgs.metrics.gaussian_window` as a tensor."""
    key = (size, sigma, dtype)
    w = _windows.get(key)
    if w is None:
        w = _windows[key] = torch.from_numpy(gaussian_window(size, sigma)).to(dtype)
    return w


def shift_blur(x: torch.Tensor, w) -> torch.Tensor:
    """Zero-padded separable filter with a symmetric window ``w`` (a list), as shifted in-place
    adds along the last two axes: 2 x 11 passes over the image, faster on a CPU than dense banded
    products."""
    r = len(w) // 2
    y = x * w[r]
    for k in range(r):
        o = r - k
        y[..., o:, :].add_(x[..., :-o, :], alpha=w[k])
        y[..., :-o, :].add_(x[..., o:, :], alpha=w[k])
    z = y * w[r]
    for k in range(r):
        o = r - k
        z[..., o:].add_(y[..., :-o], alpha=w[k])
        z[..., :-o].add_(y[..., o:], alpha=w[k])
    return z


class Blur(torch.autograd.Function):
    """The filter as an autograd op: with a symmetric window and zero padding it is self-adjoint,
    so its backward is the same filter applied to the incoming gradient."""

    @staticmethod
    def forward(ctx, x, w):
        ctx.w = w
        return shift_blur(x, w)

    @staticmethod
    def backward(ctx, g):
        return shift_blur(g, ctx.w), None


def blur(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (B, 1, H, W) with zero padding ('same' size).

    Shifted adds (see :func:`shift_blur`) with a hand-written backward, which is the filter
    itself; a single-channel convolution with a thin kernel is several times slower on CPUs, and
    dense banded matrix products do ~20x the needed arithmetic."""
    wl = w.tolist()
    if wl != wl[::-1]:
        raise InputError("the SSIM window must be symmetric")
    return Blur.apply(x, wl)


def target_maps(b: torch.Tensor, size: int = WINDOW, sigma: float = SIGMA):
    """The blurred mean and second moment of a fixed image ``b`` ((H, W) or (B, H, W)): computed
    once per measured projection, they save two of SSIM's five filter passes every iteration."""
    b = b.reshape(-1, 1, *b.shape[-2:])
    maps = blur(torch.cat([b, b * b], 0), window(size, sigma, b.dtype))
    n = b.shape[0]
    return maps[:n], maps[n:]



class SSIMError(ClgsError, ValueError):
    """Inputs the OpenCL image loss cannot take, with what to do about them."""




def _padded(x: np.ndarray, wp: int) -> np.ndarray:
    """(B, H, W) -> (B, H, wp) C-contiguous, zeros in the added columns, 64-byte aligned: the
    kernels read these rows as aligned vectors, and a CPU device uses this very memory."""
    dt = np.dtype(x.dtype)
    nbytes = x.shape[0] * x.shape[1] * wp * dt.itemsize
    raw = np.zeros(nbytes + 64, np.uint8)
    off = (-raw.ctypes.data) % 64
    out = raw[off:off + nbytes].view(dt).reshape(x.shape[:2] + (wp,))
    out[..., :x.shape[2]] = x
    return out


class SSIMTarget:
    """A fixed target ``b`` prepared for the kernels: ``b`` and its blurred mean and second
    moment (:func:`target_maps`), padded with zeros to a multiple of 8 columns.

    ``maps``: ``(mu_b, bb)`` already computed (e.g. cached by the torch path), else computed
    here. On GPUs the arrays are uploaded on first use and kept on the device."""

    def __init__(self, b, maps=None):
        b = torch.as_tensor(b).detach()
        if b.dim() == 2:
            b = b[None]
        if b.dim() != 3 or b.shape[-1] < 1 or b.shape[-2] < 1:
            raise SSIMError(f"the target must be (H, W) or (B, H, W) with H, W >= 1, got {tuple(b.shape)}")
        dt = np.dtype(str(b.dtype).replace("torch.", ""))
        real_name(dt, "images", SSIMError)
        if maps is None:
            with torch.no_grad():
                maps = target_maps(b, WINDOW, SIGMA)
        mu_b, bb = (m.detach().reshape(b.shape).to(b.dtype) for m in maps)
        self.shape = tuple(b.shape)
        self.dtype = dt
        B, H, W = self.shape
        self.nseg = -(-W // 8)
        wp = 8 * self.nseg
        self.arrays = {name: _padded(t.contiguous().numpy(), wp)
                       for name, t in (("b", b), ("mub", mu_b), ("bbm", bb))}
        self._device: dict = {}  # context handle -> {name: buffer}

    def buffers(self, io) -> dict:
        """The target's arrays as read-only buffers of the operator's pool ``io`` (wrapping this
        very memory on a CPU device, uploaded once otherwise), kept per context."""
        key = io.ctx.int_ptr
        bufs = self._device.get(key)
        if bufs is None:
            bufs = self._device[key] = {k: io.wrap(v) for k, v in self.arrays.items()}
        return bufs


class ImageLoss(Operator):
    """Owns the compiled programs (float / double) and the scratch buffers of the L1 + SSIM
    kernels; one instance serialises its own calls.

    :meth:`forward` returns the two means and, when asked, leaves the SSIM's filtered gradient
    coefficients on the device for :meth:`backward` (checked by a token: a backward whose
    forward was overwritten by another call recomputes it)."""

    RB_CPU, RB_GPU = 8, 1  # rows per work-item: CPUs want few, long work-items; GPUs many

    SOURCE = "ssim.cl"

    def __init__(self, ctx=None, queue=None):
        """``ctx``/``queue``: where it runs (default: the process's device)."""
        super().__init__(ctx, queue)
        self.rb = self.RB_CPU if self.cpu else self.RB_GPU
        self.local = (1, 1) if self.cpu else None
        w = window(WINDOW, SIGMA, torch.float64).tolist()
        self._w64 = w
        self._layout: dict = {}  # name -> (its buffer, the layout it was zeroed for)
        self._token = 0
        self._grad_token = None  # the forward whose coefficients the scratch T holds
        self._weights = None  # the last backward's (w_l1, w_ssim)
        self._spec = None  # (token, weights, inputs) of a backward pass the forward enqueued

    # ------------------------------------------------------------------ plumbing
    def program(self, real: str):
        return self.variant(real, lambda: self._defines(real))

    def _defines(self, real: str) -> dict:
        r = WINDOW // 2
        ws = self._w64[r:]  # centre first
        if real == "float":  # the window as torch rounds it for float32 (the literal is exact)
            ws = [float(np.float32(x)) for x in ws]
        defines = {"REAL": real, "RB": self.rb, "SC1": repr(C1), "SC2": repr(C2)}
        defines.update({f"WT{k}": repr(float(x)) for k, x in enumerate(ws)})
        return defines

    def target(self, b, maps=None) -> SSIMTarget:
        return SSIMTarget(b, maps)

    def _scratch(self, name: str, nbytes: int, layout):
        """A pooled device buffer, all zeros whenever its layout changes (its halo rows must be 0)."""
        buf = self.io.scratch(name, nbytes)
        zeroed = self._layout.get(name)
        if zeroed is None or zeroed[0] is not buf or zeroed[1] != layout:
            self.io.fill(buf, np.zeros(1, np.float64))
            self._layout[name] = (buf, layout)
        return buf

    def _launch(self, prog, name: str, gsize, *args):
        """Enqueue a kernel with this device's work-group shape (:meth:`Operator.launch`)."""
        self.launch(prog, name, gsize, self.local, *args)

    def _check(self, a: np.ndarray, target: SSIMTarget) -> np.ndarray:
        if not isinstance(target, SSIMTarget):
            raise SSIMError(f"target must be an SSIMTarget (ImageLoss.target(b)), got {type(target).__name__}")
        if a.shape != target.shape:
            raise SSIMError(f"render shape {a.shape} does not match the target's {target.shape}")
        if a.dtype != target.dtype:
            raise SSIMError(f"render is {a.dtype}, the target {target.dtype}: prepare the target in the render's dtype")
        if not (a.flags.c_contiguous and a.flags.writeable):
            a = np.array(a, order="C")  # the driver wraps writable C-ordered memory only
        return a

    # ------------------------------------------------------------------ passes
    def _forward(self, a: np.ndarray, target: SSIMTarget, grad: bool):
        """Enqueue the two forward passes; returns the (2, B, H) row sums (after waiting)."""
        B, H, W = a.shape
        nseg, dt = target.nseg, a.dtype
        prog = self.program(real_name(dt, "images", SSIMError))
        i32 = np.int32
        layout = (B, H, nseg, dt.str)
        nbytes = B * (H + 10) * nseg * 3 * 8 * dt.itemsize
        S = self._scratch(f"S{dt.itemsize}", nbytes, layout)
        T = self._scratch(f"T{dt.itemsize}", nbytes, layout)
        tb = target.buffers(self.io)
        rows = np.empty((2, B, H), dt)
        b_rows = self.io.scratch(f"rows{dt.itemsize}", rows.nbytes)
        gsize = (-(-H // self.rb), B)
        self._launch(prog, "ssim_h", gsize, i32(H), i32(W), i32(nseg), self.io.input(a), tb["b"], S, b_rows)
        self._launch(prog, "ssim_v", gsize, i32(H), i32(W), i32(nseg), i32(bool(grad)), S, tb["mub"], tb["bbm"],
                     T, b_rows)
        self.io.copy(rows, b_rows, is_blocking=True)
        return rows

    def _grad_pass(self, a: np.ndarray, target: SSIMTarget, w_l1: float, w_ssim: float):
        """Enqueue the backward pass (the forward's coefficients must be in T); returns its buffer."""
        B, H, W = a.shape
        dt = a.dtype
        n = a.size
        layout = (B, H, target.nseg, dt.str)
        T = self._scratch(f"T{dt.itemsize}", B * (H + 10) * target.nseg * 3 * 8 * dt.itemsize, layout)
        tb = target.buffers(self.io)
        b_out = self.io.scratch(f"out{dt.itemsize}", a.nbytes)
        i32 = np.int32
        prog = self.program(real_name(dt, "images", SSIMError))
        self._launch(prog, "ssim_grad", (-(-H // self.rb), B), i32(H), i32(W),
                     i32(target.nseg), dt.type(w_l1 / n), dt.type(w_ssim / n), T, self.io.input(a), tb["b"], b_out)
        return b_out

    def forward(self, a: np.ndarray, target: SSIMTarget, grad: bool = False):
        """(mean |a - b|, mean SSIM) as Python floats for ``a`` (B, H, W) float32/float64;
        ``grad``: also keep what :meth:`backward` needs (sets ``last_token``).

        With ``grad``, the backward pass is also enqueued right away with the weights of the last
        backward (training repeats them every iteration), to run while the caller goes on;
        :meth:`backward` then only collects it (any other weights: it runs again)."""
        with self.call():
            a = self._check(a, target)
            try:
                rows = self._forward(a, target, grad)
            finally:
                self.io.release()
                self._spec = None  # its pass is done (in-order queue): its inputs may go
            self._token += 1
            self.last_token = self._token
            self._grad_token = self._token if grad else None
            if grad and self._weights is not None:
                try:
                    self._grad_pass(a, target, *self._weights)
                    self._spec = (self._token, self._weights, list(self.io.keep))  # inputs alive till collected
                finally:
                    self.io.release()
            n = a.size
            return (float(np.sum(rows[0], dtype=np.float64)) / n, float(np.sum(rows[1], dtype=np.float64)) / n)

    def backward(self, a: np.ndarray, target: SSIMTarget, w_l1: float, w_ssim: float, token=None) -> np.ndarray:
        """d(w_l1 * mean|a - b| + w_ssim * mean SSIM)/da, (B, H, W). ``token``: the ``last_token``
        of the forward of this very ``a`` (with ``grad=True``); otherwise the forward is redone."""
        with self.call():
            a = self._check(a, target)
            out = np.empty(a.shape, a.dtype)
            weights = (float(w_l1), float(w_ssim))
            spec, self._spec = self._spec, None
            try:
                if token is None or token != self._grad_token:
                    self._forward(a, target, True)
                    self._grad_token = None
                    spec = None
                if spec is not None and spec[0] == token and spec[1] == weights:
                    b_out = self.io.pooled(f"out{a.dtype.itemsize}")  # already enqueued by the forward
                else:
                    b_out = self._grad_pass(a, target, *weights)
                self.io.copy(out, b_out, is_blocking=True)
            finally:
                self.io.release()
            self._weights = weights
            return out


def default_image_loss() -> ImageLoss:
    """The process-wide instance (programs and scratch buffers shared by every call)."""
    return shared(ImageLoss)


class _L1DSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, target, op):
        x = a.detach().reshape(target.shape).contiguous().numpy()
        grad = bool(ctx.needs_input_grad[0])
        l1, s = op.forward(x, target, grad=grad)
        ctx.save_for_backward(a)
        ctx.args = (target, op, op.last_token if grad else None)
        return a.new_tensor(l1), a.new_tensor(1.0 - s)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_l1, g_dssim):
        a, = ctx.saved_tensors
        target, op, token = ctx.args
        x = a.detach().reshape(target.shape).contiguous().numpy()
        g = op.backward(x, target, float(g_l1), -float(g_dssim), token)
        return torch.from_numpy(g).reshape(a.shape), None, None


def l1_dssim(a: torch.Tensor, target: SSIMTarget, op: ImageLoss | None = None):
    """``(mean |a - b|, 1 - mean SSIM(a, b))`` of a render ``a`` against a prepared target (same
    shape, (H, W) or (B, H, W), float32 or float64, CPU tensor); differentiable wrt ``a``."""
    if not isinstance(a, torch.Tensor):
        raise SSIMError(f"the render must be a torch tensor, got {type(a).__name__}")
    if a.device.type != "cpu":
        raise SSIMError(f"the render is on {a.device}; the OpenCL image loss takes CPU tensors")
    if not isinstance(target, SSIMTarget):
        raise SSIMError(f"target must be an SSIMTarget (ImageLoss.target(b)), got {type(target).__name__}")
    shape = tuple(a.shape) if a.dim() == 3 else (1, *a.shape)
    if a.dim() not in (2, 3) or shape != target.shape:
        raise SSIMError(f"render shape {tuple(a.shape)} does not match the target's {target.shape}")
    if a.dtype not in (torch.float32, torch.float64):
        raise SSIMError(f"the render must be float32 or float64, got {a.dtype}")
    return _L1DSSIM.apply(a, target, op or default_image_loss())
