"""A set of 3D Gaussians with R2-Gaussian's parameterisation, its initialisation, and
densification / pruning.

A :class:`GaussianSet` keeps *raw* parameters (the leaves Adam updates) and exposes the
*activated* tensors every kernel consumes:

* ``means``: (N, 3) scene coordinates, used as they are.
* ``densities``: ``softplus(raw)``, so a density never goes negative and a gradient step cannot
  flip its sign.
* ``scales``: standard deviations in scene units, either bounded,
  ``s_min + (s_max - s_min) sigmoid(raw)`` with ``s_min, s_max`` fractions of the volume's
  extent (R2-Gaussian's default: a Gaussian can neither collapse nor swallow the volume), or
  ``exp(raw)``.
* ``quats``: raw (w, x, y, z); the projector and voxelizer normalise them themselves.

Densification follows R2-Gaussian's schedule (:class:`Densifier`): every 100 iterations from 500
to 15 000, Gaussians whose mean view-space gradient exceeds 5e-5 are cloned when small or split
in two (scales / 1.6) when large; Gaussians with density below 1e-5 or whose mean left the volume
box are pruned; a cap bounds the count.

The view-space gradient. Our projector differentiates with respect to the 3D mean, not a 2D
screen position, so the densifier rebuilds the gradient 3DGS and R2-Gaussian accumulate from it:
the 3D gradient's components along the detector axes ``e_u, e_v`` are the gradient with respect
to the Gaussian's position on the detector, carried back to the Gaussian's depth; multiplying
each by the half-width of the detector at that depth (``half_width_u * |p - source| / DSD`` in cone
beam, ``half_width_u`` in parallel beam) expresses it per normalised device coordinate, the unit
of the 5e-5 threshold. Its per-view norm is summed over the views in which the Gaussian received
a gradient and divided by their count.

Split / clone densities: the projections are line integrals, so both operations keep each
Gaussian's integral (its mass ``rho (2 pi)^1.5 s_x s_y s_z``) and the rendered projections barely
move: a clone and its original each keep half the density; the two children of a split (positions
drawn from the parent, scales / 1.6 as in 3DGS) each get ``rho 1.6^3 / 2``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from clgs.errors import InputError
from clgs.reference.gaussians import quaternion_to_rotation

PARAM_NAMES = ("means", "scales", "quats", "densities")


def inverse_softplus(x: torch.Tensor) -> torch.Tensor:
    """softplus^-1, accurate for small and large x (x > 0)."""
    x = torch.clamp(x, min=torch.finfo(x.dtype).tiny)
    return torch.where(x > 20, x, x + torch.log(-torch.expm1(-x)))


@dataclass
class Schedule:
    """A learning rate: ``init`` until ``start``; 0 before ``start`` when ``frozen_before_start``;
    then log-linear from ``init`` to ``final`` over ``steps`` iterations, ``final`` after.
    ``final=None`` keeps it constant."""

    init: float
    final: float | None = None
    steps: int = 1
    start: int = 0
    frozen_before_start: bool = False

    def __call__(self, iteration: int) -> float:
        if iteration < self.start:
            return 0.0 if self.frozen_before_start else self.init
        if self.final is None or self.final == self.init:
            return self.init
        t = min(max((iteration - self.start) / max(self.steps, 1), 0.0), 1.0)
        return math.exp((1 - t) * math.log(self.init) + t * math.log(self.final))

    def to_dict(self) -> dict:
        return dict(init=self.init, final=self.final, steps=self.steps, start=self.start,
                    frozen_before_start=self.frozen_before_start)


def r2gs_schedules(iterations: int, scale: float = 1.0) -> dict:
    """R2-Gaussian's learning rates, with the exponential decays spread over ``iterations``, each
    multiplied by ``scale``."""
    k = float(scale)
    return {
        "means": Schedule(2e-4 * k, 2e-5 * k, iterations),
        "densities": Schedule(1e-2 * k, 1e-3 * k, iterations),
        "scales": Schedule(5e-3 * k, 5e-4 * k, iterations),
        "quats": Schedule(1e-3 * k, 1e-4 * k, iterations),
    }


def _transposed(x: torch.Tensor) -> torch.Tensor:
    """A contiguous copy of the (K, N) <-> (N, K) transpose of a 2D tensor, made by writing through
    a transposed view of the destination: faster on a CPU than ``x.t().contiguous()`` for K = 3..6
    columns (the copy then reads ``x`` in order). No autograd."""
    out = x.new_empty((x.shape[1], x.shape[0]))
    out.t().copy_(x)
    return out


class GaussianSet:
    """Raw parameters of N Gaussians, their activations and learning-rate schedules.

    ``box`` = half-extents (x, y, z) of the volume in scene units (pruning and the scale bounds).
    ``scale_bounds`` = (min, max) fractions of the volume's longest extent for sigmoid-bounded
    scales, or None for ``exp`` scales. ``densify`` marks a set the :class:`Densifier` may edit.
    """

    def __init__(self, means, scales, quats, densities, *, box, scale_bounds=(0.0005, 0.5),
                 schedules: dict | None = None, densify: bool = True, name: str = "gaussians",
                 raw: bool = False):
        self.name = name
        self.box = tuple(float(b) for b in box)
        self.extent = 2.0 * max(self.box)
        self.scale_bounds = None if scale_bounds is None else (float(scale_bounds[0]), float(scale_bounds[1]))
        self.densify = densify
        self.schedules = dict(schedules or r2gs_schedules(30_000))
        dt = torch.as_tensor(means).dtype if torch.is_tensor(means) else torch.float32
        t = lambda a: torch.as_tensor(a, dtype=dt).detach().clone()  # noqa: E731
        means, scales, quats, densities = t(means), t(scales), t(quats), t(densities)
        n = means.shape[0]
        if means.shape != (n, 3) or scales.shape != (n, 3) or quats.shape != (n, 4) or densities.shape != (n,):
            raise InputError(f"GaussianSet needs means (N,3), scales (N,3), quats (N,4), densities (N,); got "
                             f"{tuple(means.shape)}, {tuple(scales.shape)}, {tuple(quats.shape)}, "
                             f"{tuple(densities.shape)}")
        if not raw:
            scales = self.scale_inverse(scales)
            densities = inverse_softplus(densities)
        self.params = {"means": means, "scales": scales, "quats": quats, "densities": densities}
        for p in self.params.values():
            if not torch.all(torch.isfinite(p)):
                raise InputError(f"GaussianSet {name!r}: initial parameters contain NaN or Inf")
            p.requires_grad_(True)

    # ------------------------------------------------------------------ activations
    @property
    def scale_range(self):
        lo, hi = self.scale_bounds
        return lo * self.extent, hi * self.extent

    def scale_activation(self, raw):
        if self.scale_bounds is None:
            return torch.exp(raw)
        lo, hi = self.scale_range
        return lo + (hi - lo) * torch.sigmoid(raw)

    def scale_inverse(self, s):
        if self.scale_bounds is None:
            return torch.log(torch.clamp(s, min=1e-12))
        lo, hi = self.scale_range
        u = torch.clamp((s - lo) / (hi - lo), 1e-6, 1 - 1e-6)
        return torch.log(u) - torch.log1p(-u)

    def __len__(self):
        return int(self.params["means"].shape[0])

    def tensors(self):
        """Activated (means, scales, quats, densities), differentiable to the raw parameters."""
        p = self.params
        return p["means"], self.scale_activation(p["scales"]), p["quats"], F.softplus(p["densities"])

    def parameters(self):
        """(name, tensor, schedule) of each trainable leaf."""
        return [(k, v, self.schedules[k]) for k, v in self.params.items()]

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        return {k: v.detach().clone() for k, v in self.params.items()}

    def load_state_dict(self, state: dict) -> None:
        for k in self.params:
            self.params[k] = state[k].detach().clone().requires_grad_(True)

    def to_numpy(self) -> dict:
        """Activated parameters as float32 NumPy arrays (for the ``.npz`` output)."""
        with torch.no_grad():
            m, s, q, d = self.tensors()
            q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(1e-12)
            return {"means": m.numpy().astype(np.float32), "scales": s.numpy().astype(np.float32),
                    "quats": q.numpy().astype(np.float32), "densities": d.numpy().astype(np.float32)}

    # ------------------------------------------------------------------ editing
    def edit(self, keep: torch.Tensor, new_raw: dict | None, optimizer=None) -> None:
        """Keep rows ``keep`` (bool mask or index) and append ``new_raw`` rows (raw values).

        Adam's moments follow the kept rows; appended rows start with zero moments. The optimizer's
        parameter objects are swapped in place so its param groups and state stay consistent.
        """
        for k, old in list(self.params.items()):
            kept = old.detach()[keep]
            new = kept if not new_raw else torch.cat([kept, new_raw[k].to(old.dtype)], 0)
            new = new.contiguous().requires_grad_(True)
            if optimizer is not None:
                _swap_in_optimizer(optimizer, old, new, keep, 0 if not new_raw else new_raw[k].shape[0])
            self.params[k] = new


def _swap_in_optimizer(optimizer, old, new, keep, n_new):
    state = optimizer.state.pop(old, None)
    for group in optimizer.param_groups:
        group["params"] = [new if p is old else p for p in group["params"]]
    if state:
        for key in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
            if key in state and torch.is_tensor(state[key]) and state[key].shape == old.shape:
                s = state[key][keep]
                if n_new:
                    s = torch.cat([s, s.new_zeros((n_new,) + s.shape[1:])], 0)
                state[key] = s.contiguous()
        optimizer.state[new] = state


# ---------------------------------------------------------------------- initialisation
def _nn_scale(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance from each point to its ``k`` nearest neighbours (scipy's KD-tree)."""
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n < 2:
        return np.full(n, 0.05)
    kk = min(k, n - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)
    return dist[:, 1:].mean(1)


def init_from_volume(volume, grid, *, box, n_gaussians: int = 50_000, threshold: float = 0.05,
                     density_factor: float = 0.15, seed: int = 0, **kwargs) -> GaussianSet:
    """R2-Gaussian's initialisation from an FDK volume (already in training units).

    Voxels above ``threshold`` of the volume's range (``min + threshold (max - min)``) are
    candidates; ``n_gaussians`` of them (all, when there are fewer) are drawn without replacement.
    Each Gaussian sits on its voxel centre with density ``density_factor x`` the voxel value,
    identity rotation, and an isotropic scale equal to the mean distance to its 3 nearest sampled
    neighbours.
    """
    vol = np.asarray(volume, dtype=np.float32)
    if vol.shape != tuple(grid.shape):
        raise InputError(f"volume shape {vol.shape} does not match the grid {tuple(grid.shape)}")
    if not np.all(np.isfinite(vol)):
        raise InputError("the initial volume contains NaN or Inf; check the projections")
    lo, hi = float(vol.min()), float(vol.max())
    if not hi > lo:
        raise InputError("the initial volume is constant: nothing to initialise Gaussians from "
                         "(empty projections?); use init='random'")
    idx = np.flatnonzero(vol.reshape(-1) > lo + threshold * (hi - lo))
    rng = np.random.default_rng(seed)
    if idx.size > n_gaussians:
        idx = np.sort(rng.choice(idx, size=n_gaussians, replace=False))
    k, j, i = np.unravel_index(idx, vol.shape)
    pts = np.stack([grid.origin[0] + i * grid.spacing[0], grid.origin[1] + j * grid.spacing[1],
                    grid.origin[2] + k * grid.spacing[2]], 1)
    scales = np.repeat(_nn_scale(pts)[:, None], 3, 1)
    dens = vol.reshape(-1)[idx] * density_factor
    dens = np.maximum(dens, 1e-6)  # softplus^-1 needs > 0 (only hit when the range is below 0)
    quats = np.zeros((idx.size, 4)); quats[:, 0] = 1.0
    return GaussianSet(pts.astype(np.float32), scales.astype(np.float32), quats.astype(np.float32),
                       dens.astype(np.float32), box=box, **kwargs)


def init_random(n_gaussians: int, *, box, density: float = 0.05, seed: int = 0, **kwargs) -> GaussianSet:
    """Gaussians uniformly spread over the volume box, with a constant density and the
    nearest-neighbour isotropic scale (for scenes without a usable FDK)."""
    rng = np.random.default_rng(seed)
    b = np.asarray(box, float)
    pts = (rng.random((n_gaussians, 3)) * 2 - 1) * b
    scales = np.repeat(_nn_scale(pts)[:, None], 3, 1)
    quats = np.zeros((n_gaussians, 4)); quats[:, 0] = 1.0
    return GaussianSet(pts.astype(np.float32), scales.astype(np.float32), quats.astype(np.float32),
                       np.full(n_gaussians, density, np.float32), box=box, **kwargs)


# ---------------------------------------------------------------------- densification
class Densifier:
    """Trainer hook: accumulates view-space gradients and densifies / prunes sets marked ``densify``.

    R2-Gaussian's defaults: every ``interval`` (100) iterations from ``start`` (500) to ``until``
    (15 000); ``grad_threshold`` 5e-5; a Gaussian is "small" (cloned) when its largest scale is at
    most ``scale_threshold`` (0.1) x the volume's extent, else split in 2 with scales / 1.6;
    a clone and its original share the density, each split child gets ``split_density`` (0.5) x
    its parent's (R2-Gaussian's rule: a split drops most of the parent's integral and the fit
    rebuilds it); prune below ``min_density`` (1e-5) or outside the box; never more than
    ``max_gaussians`` in a set (the candidates with the largest gradients go first).
    """

    def __init__(self, geometry, *, start=500, until=15_000, interval=100, grad_threshold=5e-5,
                 scale_threshold=0.1, min_density=1e-5, max_gaussians=500_000, split_factor=1.6,
                 split_density=0.5):
        self.geometry = geometry
        self.start, self.until, self.interval = int(start), int(until), int(interval)
        self.grad_threshold, self.scale_threshold = float(grad_threshold), float(scale_threshold)
        self.min_density, self.max_gaussians = float(min_density), int(max_gaussians)
        self.split_factor, self.split_density = float(split_factor), float(split_density)
        self.stats: dict = {}  # set name -> (grad_sum (N,), count (N,))
        vec = geometry.view_vectors(scene=True)
        self._vectors = torch.as_tensor(vec, dtype=torch.float64)
        nv, nu = geometry.nDetector
        # per view (a vector geometry may change pixel size and source distance from view to view)
        self._half = np.stack([0.5 * nu * np.linalg.norm(vec[:, 6:9], axis=1),
                               0.5 * nv * np.linalg.norm(vec[:, 9:12], axis=1)], 1)
        self._dsd = geometry.source_detector_distance() * geometry.scale
        self._axes: dict = {}  # (view, dtype) -> detector axes scaled to normalised coordinates

    def _sets(self, trainer):
        return [s for s in trainer.sets if getattr(s, "densify", False)]

    def view_space_grad(self, means: torch.Tensor, grad: torch.Tensor, view: int) -> torch.Tensor:
        """(N,) norm of the gradient per normalised detector coordinate (see the module doc)."""
        return self._view_space_grad(means, _transposed(grad), view)

    # The statistics run every iteration on all N Gaussians: they work on (3, N) columns (a
    # small matrix product, reductions over the short axis) because torch's norms and broadcasts
    # along a length-3 inner axis are much slower on a CPU.
    def _view_space_grad(self, means: torch.Tensor, grad_t: torch.Tensor, view: int) -> torch.Tensor:
        axes = self._axes.get((view, grad_t.dtype))
        if axes is None:  # (2, 3): unit detector axes times the detector's half-widths
            vec = self._vectors[view]
            eu = vec[6:9] / torch.linalg.vector_norm(vec[6:9])
            ev = vec[9:12] / torch.linalg.vector_norm(vec[9:12])
            axes = torch.stack([eu * float(self._half[view, 0]), ev * float(self._half[view, 1])], 0).to(grad_t.dtype)
            self._axes[(view, grad_t.dtype)] = axes
        gu, gv = torch.mm(axes, grad_t).unbind(0)
        norm = torch.sqrt(gu * gu + gv * gv)
        if self.geometry.mode == "cone":  # the depth factor is the same on both axes
            rel = _transposed(means.detach()) - self._vectors[view, 0:3].to(grad_t.dtype)[:, None]
            norm = norm * (torch.sqrt((rel * rel).sum(0)) / float(self._dsd[view]))
        return norm

    def after_backward(self, trainer, ctx) -> None:
        it = trainer.iteration
        if it >= self.until:
            return
        offsets, start = {}, 0
        for s in trainer.sets:
            offsets[s.name] = start
            start += len(s)
        group = getattr(ctx, "group", [ctx])
        # each view of the step contributes its own statistic, as if it had had a step of its own:
        # a multi-view step averages the views' losses, so a view's projection gradient is 1/k of it
        grads = [(c.view, getattr(c, "render_means_grad", None)) for c in group]
        if any(g is None or g.shape[0] != start for _, g in grads):  # no render: the parameters' gradient
            grads = [(ctx.view, None)]
        k = float(len(grads))
        for s in self._sets(trainer):
            n = len(s)
            acc, cnt = self.stats.get(s.name, (None, None))
            for view, render_grad in grads:
                if render_grad is not None:
                    # the projection's share only, as R2-Gaussian's view-space gradient
                    g = render_grad[offsets[s.name]:offsets[s.name] + n]
                    if k > 1:
                        g = g * k
                else:
                    g = s.params["means"].grad
                if g is None:
                    continue
                if acc is None or acc.shape[0] != n:
                    acc, cnt = torch.zeros(n, dtype=g.dtype), torch.zeros(n, dtype=g.dtype)
                gt = _transposed(g)
                seen = (gt[0] != 0) | (gt[1] != 0) | (gt[2] != 0)
                if render_grad is None and s.params["densities"].grad is not None:
                    seen |= s.params["densities"].grad != 0
                # a Gaussian with a zero mean gradient adds exactly 0, so no mask is needed here
                acc = acc + self._view_space_grad(s.params["means"], gt, view)
                cnt = cnt + seen.to(g.dtype)
            if acc is not None:
                self.stats[s.name] = (acc, cnt)

    def due(self, iteration: int) -> bool:
        """True after iteration ``iteration`` (1-based count of completed steps) when densifying."""
        return self.start <= iteration <= self.until and iteration % self.interval == 0

    def on_iteration(self, trainer) -> None:
        if not self.due(trainer.iteration):
            return
        for s in self._sets(trainer):
            self.densify_and_prune(s, trainer.optimizer, trainer.generator)
            self.stats.pop(s.name, None)

    def densify_and_prune(self, s: GaussianSet, optimizer, generator) -> dict:
        """One densify + prune pass on set ``s``; returns counts (cloned, split, pruned)."""
        with torch.no_grad():
            n = len(s)
            acc, cnt = self.stats.get(s.name, (torch.zeros(n), torch.zeros(n)))
            if acc.shape[0] != n:
                acc, cnt = torch.zeros(n), torch.zeros(n)
            grad = acc / cnt.clamp_min(1)
            means, scales, quats, dens = s.tensors()
            cand = grad >= self.grad_threshold
            budget = max(self.max_gaussians - n, 0)
            if int(cand.sum()) > budget:  # largest gradients first, ties by index (deterministic)
                order = torch.argsort(-grad, stable=True)[:budget]
                cand = torch.zeros_like(cand)
                cand[order] = True
            small = scales.max(1).values <= self.scale_threshold * s.extent
            clone, split = cand & small, cand & ~small
            raw = s.params
            # clone: a copy at the same place; the pair shares the density
            half_d = inverse_softplus(dens[clone] * 0.5)
            clone_raw = {k: raw[k].detach()[clone] for k in PARAM_NAMES}
            clone_raw["densities"] = half_d
            # split: two children drawn from the parent, scales / 1.6, each with split_density x
            # the parent's density
            ns = int(split.sum())
            r = quaternion_to_rotation(quats[split])
            eps = torch.randn((2, ns, 3), generator=generator, dtype=means.dtype)
            children = means[split][None] + torch.einsum("nij,knj->kni", r, eps * scales[split][None])
            child_scales = s.scale_inverse(scales[split] / self.split_factor)
            split_raw = {
                "means": children.reshape(2 * ns, 3),
                "scales": child_scales.repeat(2, 1),
                "quats": raw["quats"].detach()[split].repeat(2, 1),
                "densities": inverse_softplus(dens[split] * self.split_density).repeat(2),
            }
            # original of a clone keeps half its density; a split parent is removed
            new_dens_raw = raw["densities"].detach().clone()
            new_dens_raw[clone] = half_d
            raw["densities"].data.copy_(new_dens_raw)
            new = {k: torch.cat([clone_raw[k], split_raw[k]], 0) for k in PARAM_NAMES}
            # prune: parents of splits, faint ones, and those outside the box (new ones included)
            all_means = torch.cat([means, new["means"]], 0)
            all_dens = torch.cat([F.softplus(raw["densities"].detach()), F.softplus(new["densities"])], 0)
            box = torch.as_tensor(s.box, dtype=means.dtype)
            inside = torch.all(all_means.abs() <= box, dim=1)
            keep_all = inside & (all_dens >= self.min_density)
            keep_all[:n] &= ~split
            keep_old = keep_all[:n]
            keep_new = keep_all[n:]
            new = {k: v[keep_new] for k, v in new.items()}
            s.edit(keep_old, new, optimizer)
            return {"cloned": int(clone.sum()), "split": ns, "pruned": int((~keep_all).sum()) - ns,
                    "count": len(s)}

    def state_dict(self) -> dict:
        out = {}
        for name, (acc, cnt) in self.stats.items():
            out[f"{name}.grad"] = acc.clone()
            out[f"{name}.count"] = cnt.clone()
        return out

    def load_state_dict(self, state: dict) -> None:
        self.stats = {}
        for key, v in state.items():
            name, kind = key.rsplit(".", 1)
            acc, cnt = self.stats.get(name, (None, None))
            self.stats[name] = (v.clone(), cnt) if kind == "grad" else (acc, v.clone())
