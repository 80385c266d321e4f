"""Diffeomorphic registration of a subject's shape to the template with a stationary velocity field.

We look for v on the model grid such that, with phi = exp(v) (template -> subject),

    S(phi(x)) ~ T(x)          for x on the template (model) grid,

where T and S are the template's and the subject's signed distances (mm, negative inside),
compared through ``tanh(d / w)``: a smoothed label whose soft edge (``w`` = a couple of cells)
gives gradients near the surface and saturates far from it, so distant structures do not pull.
The velocity is regularised by its diffusion energy ``mean |grad v|^2`` plus a small
``mean |v|^2``. Coarse to fine: each level has its own grid over the same box (the velocity is
resampled when moving to the next), the soft edge follows the level's cell size, Adam steps
the velocity. Everything is torch on the CPU; a 48^3 model grid takes a few seconds a subject.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from clgs.errors import InputError
from clgs.shape.model import exp_velocity, jacobian_determinant, sample_field, squarings_for
from clgs.shape.template import box_grid, grid_points, zyx_triple


@dataclass(frozen=True)
class RegistrationSettings:
    """Knobs of :func:`register` (all stored in model metadata, so builds are reproducible).

    levels: cells along the longest side per level, coarse to fine; the last one is replaced by
    the model grid itself. iterations: Adam steps per level. lr: Adam step in cells of the level.
    edge_cells: width of the soft label edge in cells. smooth: weight of the diffusion energy.
    magnitude: weight of ``mean |v|^2`` (mm^-2 scaled by the cell size)."""

    levels: tuple = (16, 32, 0)
    iterations: tuple = (80, 60, 40)
    lr: float = 0.25
    edge_cells: float = 1.5
    smooth: float = 0.01
    magnitude: float = 1e-4
    seed: int = 0

    def __post_init__(self):
        if len(self.levels) != len(self.iterations) or not self.levels:
            raise InputError("levels and iterations must be non-empty and of the same length")
        if self.lr <= 0 or self.edge_cells <= 0 or self.smooth < 0 or self.magnitude < 0:
            raise InputError(f"bad registration settings: {self}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["levels"], d["iterations"] = list(self.levels), list(self.iterations)
        return d

    @classmethod
    def from_dict(cls, d: dict | None) -> RegistrationSettings:
        d = dict(d or {})
        for k in ("levels", "iterations"):
            if k in d:
                d[k] = tuple(int(x) for x in d[k])
        return cls(**d)


@dataclass
class Registration:
    """A registration result: the velocity (3, Z, Y, X) mm on the model grid and residuals.

    residuals: surface_mean_mm / surface_max_mm (distance from the mapped template surface to
    the subject's surface), dice (template label vs the subject's label pulled back),
    loss, min_jacobian (<= 0 would mean folding), n_squarings."""

    velocity: np.ndarray
    spacing: tuple
    origin: tuple
    residuals: dict = field(default_factory=dict)


def _diffusion(v: torch.Tensor, spacing) -> torch.Tensor:
    dz, dy, dx = spacing
    gz = (v[:, 1:] - v[:, :-1]) / dz
    gy = (v[:, :, 1:] - v[:, :, :-1]) / dy
    gx = (v[:, :, :, 1:] - v[:, :, :, :-1]) / dx
    return (gz ** 2).mean() + (gy ** 2).mean() + (gx ** 2).mean()


class _Adam:
    """Adam with ONE second-moment scale for the whole field (the largest per-voxel RMS).

    Per-voxel Adam would step every voxel by about ``lr`` whatever its gradient, so voxels far
    from any edge, whose gradients are only noise, would drift; with a shared scale the step is
    proportional to the gradient and the biggest one moves by about ``lr``."""

    def __init__(self, p, lr, betas=(0.9, 0.999), eps=1e-12):
        self.p, self.lr, self.b1, self.b2, self.eps = p, lr, betas[0], betas[1], eps
        self.m = torch.zeros_like(p)
        self.v = torch.zeros_like(p)
        self.t = 0

    @torch.no_grad()
    def step(self):
        g = self.p.grad
        self.t += 1
        self.m.mul_(self.b1).add_(g, alpha=1 - self.b1)
        self.v.mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
        mhat = self.m / (1 - self.b1 ** self.t)
        scale = float((self.v.max() / (1 - self.b2 ** self.t)).sqrt()) + self.eps
        self.p.sub_(self.lr * mhat / scale)


class _threads:
    """Run torch with ``n`` intra-op threads inside the block (None: leave as is)."""

    def __init__(self, n):
        self.n, self.old = n, None

    def __enter__(self):
        if self.n:
            self.old = torch.get_num_threads()
            torch.set_num_threads(int(self.n))

    def __exit__(self, *exc):
        if self.old:
            torch.set_num_threads(self.old)


def register(fixed_sdf, fixed_spacing, fixed_origin, moving_sdf, moving_spacing, moving_origin,
             settings: RegistrationSettings | None = None, surface_points=None,
             init_velocity=None, threads: int | None = 1) -> Registration:
    """Register a subject (moving) to the template (fixed); both given as signed distances (mm).

    fixed_*: the template's signed distance on the MODEL grid (the velocity's grid).
    moving_*: the subject's signed distance on any grid covering it with a margin.
    surface_points: template surface points (N, 3) mm for the surface residual (optional).
    init_velocity: a starting velocity on the model grid (e.g. the population mean).
    threads: torch threads (1 by default: the fields are small, and extra threads mostly wait on a
    busy machine; the builder can run subjects side by side instead).
    Returns the velocity of phi = exp(v) mapping template points onto the subject."""
    with _threads(threads):
        return _register(fixed_sdf, fixed_spacing, fixed_origin, moving_sdf, moving_spacing, moving_origin,
                         settings, surface_points, init_velocity)


def _register(fixed_sdf, fixed_spacing, fixed_origin, moving_sdf, moving_spacing, moving_origin,
              settings, surface_points, init_velocity) -> Registration:
    s = settings or RegistrationSettings()
    torch.manual_seed(s.seed)
    dtype = torch.float32
    f_sp, f_or = zyx_triple("spacing", fixed_spacing), zyx_triple("origin", fixed_origin)
    m_sp, m_or = zyx_triple("spacing", moving_spacing), zyx_triple("origin", moving_origin)
    fixed = torch.as_tensor(np.asarray(fixed_sdf, np.float32))[None]
    moving = torch.as_tensor(np.asarray(moving_sdf, np.float32))[None]
    if fixed.dim() != 4 or moving.dim() != 4:
        raise InputError("fixed and moving signed distances must be (Z, Y, X) volumes")
    if not (torch.isfinite(fixed).all() and torch.isfinite(moving).all()):
        raise InputError("signed distances contain NaN or Inf")
    model_shape = tuple(fixed.shape[1:])
    lo = np.asarray(f_or[::-1])
    hi = lo + (np.asarray(model_shape[::-1]) - 1) * np.asarray(f_sp[::-1])
    longest = max(model_shape)

    v = None
    if init_velocity is not None:
        v = torch.as_tensor(np.asarray(init_velocity, np.float32))
        if tuple(v.shape) != (3,) + model_shape:
            raise InputError(f"init_velocity must be (3, {model_shape}), got {tuple(v.shape)}")
    prev = None  # (field, spacing, origin)
    loss_value = float("nan")
    for level, (cells, iters) in enumerate(zip(s.levels, s.iterations)):
        last = level == len(s.levels) - 1
        if last or cells <= 0 or cells >= longest:
            shape, sp, org = model_shape, f_sp, f_or
            target = fixed[0]
        else:
            shape, sp, org = box_grid(lo, hi, max_cells=int(cells))
            target = sample_field(fixed, torch.as_tensor(grid_points(shape, sp, org).reshape(-1, 3), dtype=dtype),
                                  f_sp, f_or).reshape(shape)
        pts = torch.as_tensor(grid_points(shape, sp, org), dtype=dtype)
        flat = pts.reshape(-1, 3)
        if prev is None:
            start = (sample_field(v, flat, f_sp, f_or).T.reshape(3, *shape) if v is not None
                     else torch.zeros((3,) + tuple(shape), dtype=dtype))
        else:
            start = sample_field(prev[0], flat, prev[1], prev[2]).T.reshape(3, *shape)
        vel = start.clone().requires_grad_(True)
        h = min(sp)
        width = s.edge_cells * h
        t_soft = torch.tanh(target / width)
        adam = _Adam(vel, lr=s.lr * h)
        for _ in range(int(iters)):
            vel.grad = None
            u = exp_velocity(vel, sp)
            warped = sample_field(moving, flat + u.reshape(3, -1).T, m_sp, m_or).reshape(shape)
            data = ((torch.tanh(warped / width) - t_soft) ** 2).mean()
            reg = s.smooth * _diffusion(vel, sp) * h * h / 1.0 + s.magnitude * (vel ** 2).mean() / (h * h)
            loss = data + reg
            loss.backward()
            adam.step()
            loss_value = float(loss.detach())
        prev = (vel.detach(), sp, org)
        if not math.isfinite(loss_value):
            raise FloatingPointError("registration diverged (non-finite loss): lower lr or raise smooth")

    v = prev[0]
    with torch.no_grad():
        u = exp_velocity(v, f_sp)
        flat = torch.as_tensor(grid_points(model_shape, f_sp, f_or).reshape(-1, 3), dtype=dtype)
        warped = sample_field(moving, flat + u.reshape(3, -1).T, m_sp, m_or).reshape(model_shape)
        a, b = warped < 0, fixed[0] < 0
        dice = float(2 * (a & b).sum() / max(int(a.sum() + b.sum()), 1))
        residuals = {"dice": dice, "loss": loss_value, "n_squarings": squarings_for(v, f_sp),
                     "min_jacobian": float(jacobian_determinant(u, f_sp).min())}
        if surface_points is not None:
            sp_t = torch.as_tensor(np.asarray(surface_points, np.float32))
            mapped = sp_t + sample_field(u, sp_t, f_sp, f_or)
            d = sample_field(moving, mapped, m_sp, m_or).abs()[:, 0]
            residuals["surface_mean_mm"] = float(d.mean())
            residuals["surface_max_mm"] = float(d.max())
    return Registration(v.numpy().astype(np.float32), f_sp, f_or, residuals)
