"""The shape-guided Gaussian set: Gaussians whose centres follow a shape model,
``p_j = p_ref_j + u(alpha)(p_ref_j)``, so one vector of mode coefficients moves them all and keeps
the bone plausible. Their scale, rotation and density are free, as any :class:`GaussianSet`'s.

With a fitted size ``s`` the model's bone is also scaled about a fixed centre ``c``:
``p_j = c + s (p_ref_j + u(alpha)(p_ref_j) - c)``. The modes of a shape model built from one
population describe its shapes at that population's sizes; a femur of 355 or 558 mm lies beyond
what they can stretch to, and ``s`` (one number, no prior) takes that part. With a fitted length
``k`` as well, the scaling along the leg (z) is ``s k``: a femur longer or shorter for its girth
than the model's (``diag(s, s, s k)``; docs/methods.md).

With a residual (:mod:`clgs.shape.residual`) a smooth displacement ``r(theta)`` on the template,
beyond the modes' span, is added to theirs:
``p_j = c + s (p_ref_j + u(alpha)(p_ref_j) + r(theta)(p_ref_j) - c)``."""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from clgs.fit.fixed_points import FixedPointSampler
from clgs.fit.gaussians import GaussianSet
from clgs.shape.model import exp_velocity, squarings_for
from clgs.shape.size import LEG_AXIS
from clgs.shape.template import zyx_triple


class ShapeGuidedSet(GaussianSet):
    """Gaussians whose centres are ``p_ref + u(alpha)(p_ref)`` (mm), mapped to the scene.

    Leaves: ``alpha`` (M,), raw scales, quaternions, raw densities. ``p_ref`` is fixed."""

    MIN_SQUARINGS = 2
    # The centres between refreshes of exp(v): u(alpha) = u(a0) + J (alpha - a0), J the secant
    # of u over alpha_m = a0_m +- LINEAR_TOL, refreshed (2M + 1 forward-only exponentiations, no
    # backward) once some |alpha_m - a0_m| exceeds LINEAR_TOL. While alpha moves fast (the last
    # step over LINEAR_TOL / 4: early, when its learning rate is high) a linearisation would last
    # a few iterations only, so there the exact path runs. How close it stays to the exact map:
    # docs/methods.md (tests/test_fixed_points.py checks a small model). None: the exact path every
    # iteration.
    LINEAR_TOL = 0.05

    def __init__(self, p_ref_mm, scales, quats, densities, *, shape_model, geometry, box, scale_bounds,
                 schedules, alpha=None, name: str = "shape", raw: bool = False, sampler=None,
                 size: float | None = None, size_centre_mm=None, residual=None, residual_theta=None,
                 length: float | None = None):
        dt = torch.float32
        self.sampler = sampler  # a FieldSampler (OpenCL) or None (torch's grid_sample)
        self.shape_model = shape_model.to(dt) if shape_model.dtype != dt else shape_model
        self.p_ref = torch.as_tensor(np.asarray(p_ref_mm, np.float64), dtype=dt)
        self._origin = torch.as_tensor(geometry.centre_xyz, dtype=dt)
        self._scale = float(geometry.scale)
        placeholder = torch.zeros((len(self.p_ref), 3), dtype=dt)
        super().__init__(placeholder, scales, quats, densities, box=box, scale_bounds=scale_bounds,
                         schedules=schedules, densify=False, name=name, raw=raw)
        del self.params["means"]
        a = torch.zeros(self.shape_model.n_modes, dtype=dt) if alpha is None else torch.as_tensor(alpha, dtype=dt)
        self.params = {"alpha": a.detach().clone().requires_grad_(True), **self.params}
        # the bone's size relative to the model's (None: not fitted, the model's own size)
        self.size_centre = None
        if size is not None:
            if not np.isfinite(size) or size <= 0:
                raise ValueError(f"size must be a positive number, got {size}")
            self.size_centre = torch.as_tensor(np.asarray(size_centre_mm, np.float64), dtype=dt)
            self.params["log_size"] = torch.tensor([np.log(size)], dtype=dt, requires_grad=True)
        # a length of its own along the leg (z), times the size (None: the size alone)
        if length is not None:
            if size is None:
                raise ValueError("a length factor needs a fitted size (its centre)")
            if not np.isfinite(length) or length <= 0:
                raise ValueError(f"length must be a positive number, got {length}")
            self.params["log_length"] = torch.tensor([np.log(length)], dtype=dt, requires_grad=True)
        # the residual beyond the model's span (a ResidualGrid on the model's grid, None: none)
        self.residual = residual.to(dt) if residual is not None and residual.dtype != dt else residual
        if residual is not None:
            theta = self.residual.zeros() if residual_theta is None else torch.as_tensor(residual_theta, dtype=dt)
            if tuple(theta.shape) != self.residual.coefficient_shape or tuple(residual.shape) != self.shape_model.shape:
                raise ValueError(f"residual coefficients {tuple(theta.shape)} on a grid {tuple(residual.shape)} do not "
                                 f"fit the shape model's grid {self.shape_model.shape}")
            self.params["residual"] = theta.detach().clone().requires_grad_(True)
        self.last_u = None  # the latest displacement field (detached), for the density prior
        self._at_ref = None  # FixedPointSampler at p_ref, built on first use
        self._linear = None  # (a0, u0 grid, J grid, centre offsets at a0, their J): the linearised map
        self._prev_alpha, self._step = None, 0.0  # the latest alpha seen and its step from the one before

    def __len__(self):
        return int(self.p_ref.shape[0])

    @property
    def alpha(self) -> torch.Tensor:
        return self.params["alpha"]

    def displacement(self) -> torch.Tensor:
        """u(alpha) on the model grid. Squarings follow the half-cell rule with a floor of
        ``MIN_SQUARINGS`` (2, not the model's default 4): on the femur model at alpha = 3 sigma
        the map then differs from a 12-squaring one by 0.64 mm (0.2 voxel) and costs half as much,
        which matters since this runs, forward and backward, every iteration."""
        u = exp_velocity(self.shape_model.velocity(self.alpha), self.shape_model.spacing,
                         min_squarings=self.MIN_SQUARINGS, sampler=self.sampler)
        self.last_u = u.detach()
        return u

    @property
    def fits_size(self) -> bool:
        return "log_size" in self.params

    @property
    def size(self) -> float:
        """The fitted size (1.0 without one)."""
        return float(torch.exp(self.params["log_size"].detach())[0]) if self.fits_size else 1.0

    @property
    def fits_length(self) -> bool:
        return "log_length" in self.params

    @property
    def length(self) -> float:
        """The fitted length factor along the leg (1.0 without one)."""
        return float(torch.exp(self.params["log_length"].detach())[0]) if self.fits_length else 1.0

    def _stretch(self, like: torch.Tensor, detach: bool = False) -> torch.Tensor:
        """Ones with the length factor k along the leg (LEG_AXIS: z), ones alone without one."""
        if not self.fits_length:
            return torch.ones(3, dtype=like.dtype)
        k = torch.exp(self.params["log_length"].detach() if detach else self.params["log_length"]).to(like.dtype)
        parts = [torch.ones(1, dtype=like.dtype)] * 3
        parts[LEG_AXIS] = k
        return torch.cat(parts)

    def scaled(self, points_mm: torch.Tensor) -> torch.Tensor:
        """Points of the model's frame at the fitted size: ``c + s (x - c)``, times the length
        factor along the leg where one is fitted (the points as they are without a fitted size)."""
        if not self.fits_size:
            return points_mm
        s = torch.exp(self.params["log_size"])
        if self.fits_length:
            s = s * self._stretch(points_mm)
        return self.size_centre + s * (points_mm - self.size_centre)

    def centres_mm(self, u=None) -> torch.Tensor:
        centres = self._model_centres_mm(u)
        if self.has_residual:
            centres = centres + self._at_ref_points(self.residual_field())
        return self.scaled(centres)

    @property
    def has_residual(self) -> bool:
        return "residual" in self.params

    def residual_field(self) -> torch.Tensor:
        """r(theta) (3, Z, Y, X) mm on the model grid, differentiable in theta (zeros without one)."""
        if not self.has_residual:
            return torch.zeros((3,) + self.shape_model.shape, dtype=self.p_ref.dtype)
        return self.residual.field(self.params["residual"])

    def residual_prior(self, bending: float) -> torch.Tensor:
        """The residual's prior (:meth:`clgs.shape.residual.ResidualGrid.prior`; 0 without one)."""
        if not self.has_residual:
            return torch.zeros((), dtype=self.p_ref.dtype)
        return self.residual.prior(self.params["residual"], bending)

    def _at_ref_points(self, field: torch.Tensor) -> torch.Tensor:
        """``field`` (3, Z, Y, X) sampled at ``p_ref``: p_ref never moves, so its trilinear weights
        are built once into a sparse matrix (:mod:`clgs.fit.fixed_points`); grid_sample only for
        a field of another dtype."""
        if field.dtype != self.p_ref.dtype:
            return self.shape_model.sample(field, self.p_ref)
        return self._ref_sampler()(field)

    def total_displacement(self) -> torch.Tensor:
        """u(alpha) + r(theta) (3, Z, Y, X) on the model grid, detached: the whole map's (before the size)."""
        if self.last_u is None:
            with torch.no_grad():
                self.displacement()
        if not self.has_residual:
            return self.last_u
        with torch.no_grad():
            return self.last_u + self.residual_field()

    def _model_centres_mm(self, u=None) -> torch.Tensor:
        if u is None and self.LINEAR_TOL is not None and self._one_dtype():
            out = self._linear_centres()
            if out is not None:
                return out
        u = self.displacement() if u is None else u
        return self.p_ref + self._at_ref_points(u)

    def _one_dtype(self) -> bool:
        return self.shape_model.mean.dtype == self.p_ref.dtype

    def _linear_centres(self):
        """``p_ref + u(a0)(p_ref) + Jc (alpha - a0)``, differentiable in alpha; refreshed at the
        current alpha when it has left the box of half-width LINEAR_TOL around a0; None (the
        exact path) while alpha moves fast."""
        a = self.alpha
        now = a.detach().clone()
        if self._prev_alpha is None or not torch.equal(now, self._prev_alpha):  # a new alpha: its step
            step = 0.0 if self._prev_alpha is None else float((now - self._prev_alpha).abs().max())
            self._prev_alpha, self._step = now, step
        tol = float(self.LINEAR_TOL)
        if self._linear is None or float((now - self._linear[0]).abs().max()) > tol:
            if self._step > tol / 4:
                self._linear = None
                return None
            self._linear = self._linearise(now)
        a0, u0, J, c0, Jc = self._linear
        delta = a - a0
        self.last_u = u0 + torch.tensordot(J, delta.detach(), dims=1)
        return self.p_ref + c0 + torch.tensordot(Jc, delta, dims=1)

    def _linearise(self, a0: torch.Tensor):
        """(a0, u(a0), J, their samples at p_ref): u on the model grid (3, Z, Y, X), J
        (M, 3, Z, Y, X) the central secants over +- LINEAR_TOL, all with the squaring count of a0."""
        m, h = self.shape_model, float(self.LINEAR_TOL)
        with torch.no_grad():
            v0 = m.velocity(a0)
            n = squarings_for(v0, m.spacing, self.MIN_SQUARINGS)

            def exp(a):
                return exp_velocity(m.velocity(a), m.spacing, n_squarings=n, sampler=self.sampler)

            u0 = exp_velocity(v0, m.spacing, n_squarings=n, sampler=self.sampler)
            eye = torch.eye(len(a0), dtype=a0.dtype) * h
            J = torch.stack([(exp(a0 + e) - exp(a0 - e)) / (2 * h) for e in eye])
            at = self._ref_sampler()
            c0 = at(u0)
            Jc = torch.stack([at(j) for j in J], -1)  # (N, 3, M)
        return a0, u0, J.movedim(0, -1), c0, Jc

    def _ref_sampler(self) -> FixedPointSampler:
        if self._at_ref is None:
            m = self.shape_model
            origin = torch.tensor(zyx_triple("origin", m.origin)[::-1], dtype=torch.float64)
            step = torch.tensor(zyx_triple("spacing", m.spacing)[::-1], dtype=torch.float64)
            vox = (self.p_ref.double() - origin) / step
            self._at_ref = FixedPointSampler(vox, tuple(m.mean.shape[1:]), self.p_ref.dtype)
        return self._at_ref

    def map_points(self, points_mm, alpha=None, n_squarings: int | None = None) -> torch.Tensor:
        """Template points (N, 3) mm carried onto the subject by the whole map at ``alpha`` (the
        fitted alpha when None): the model's deformation, the residual and the size; the exact
        map (no linearisation), no gradients. ``n_squarings``: fixed (a finite difference keeps
        one count on both sides); None: the half-cell rule's."""
        m = self.shape_model
        with torch.no_grad():
            a = self.alpha.detach() if alpha is None else torch.as_tensor(alpha, dtype=self.alpha.dtype)
            v = m.velocity(a)
            n = squarings_for(v, m.spacing, self.MIN_SQUARINGS) if n_squarings is None else int(n_squarings)
            u = exp_velocity(v, m.spacing, n_squarings=n, sampler=self.sampler)
            p = torch.as_tensor(np.asarray(points_mm, np.float64), dtype=self.p_ref.dtype)
            return self.scaled(p + m.sample(u + self.residual_field(), p))

    def squarings(self) -> int:
        """The squaring count of the fitted alpha (the half-cell rule's)."""
        with torch.no_grad():
            return squarings_for(self.shape_model.velocity(self.alpha.detach()), self.shape_model.spacing,
                                 self.MIN_SQUARINGS)

    def tensors_at(self, alpha, n_squarings: int | None = None):
        """:meth:`tensors` with the centres moved by the map at ``alpha`` (:meth:`map_points`),
        everything else as fitted; no gradients (for finite differences in alpha)."""
        with torch.no_grad():
            p = self.params
            means = (self.map_points(self.p_ref, alpha, n_squarings) - self._origin) * self._scale
            return means, self.scale_activation(p["scales"]), p["quats"], F.softplus(p["densities"])

    def tensors(self):
        p = self.params
        means = (self.centres_mm() - self._origin) * self._scale
        return means, self.scale_activation(p["scales"]), p["quats"], F.softplus(p["densities"])

    def to_template(self, points_mm: torch.Tensor, tissue: bool = False) -> torch.Tensor:
        """Points of the subject carried back to the template: the size undone, then x' = x - u(x'),
        two fixed-point steps (``u`` the model's displacement plus the residual). ``tissue``: the
        size undone as the tissue around the bone takes it: a larger bone's, not a smaller one's (a
        limb has a girth of its own; see :meth:`clgs.shape.priors.DensityPrior._sized_points`)."""
        total = self.total_displacement()
        if self.fits_size:
            s = torch.exp(self.params["log_size"].detach())
            k = self._stretch(points_mm, detach=True)
            # the tissue takes the bone's size and length where they are larger, never smaller
            s = torch.clamp(s, min=1.0) * torch.clamp(k, min=1.0) if tissue else s * k
            points_mm = self.size_centre + (points_mm - self.size_centre) / s
        x = points_mm
        for _ in range(2):
            x = points_mm - self.shape_model.sample(total, x, self.sampler)
        return x

    def to_numpy(self) -> dict:
        out = super().to_numpy()
        out["alpha"] = self.alpha.detach().numpy().astype(np.float32)
        if self.fits_size:
            out["size"] = np.float32(self.size)
            out["size_centre_mm"] = self.size_centre.numpy().astype(np.float32)
        if self.fits_length:
            out["length"] = np.float32(self.length)
        out["p_ref_mm"] = self.p_ref.numpy().astype(np.float32)
        if self.has_residual:  # the B-spline coefficients (mm) and their control spacing
            out["residual_mm"] = self.params["residual"].detach().numpy().astype(np.float32)
            out["residual_spacing_mm"] = np.float32(self.residual.h)
        return out

    def state_dict(self) -> dict:
        # the linearisation's anchor and the latest step: a resumed run rebuilds the same
        # linearisation from a0 (deterministic) and continues bit for bit
        empty = torch.zeros(0, dtype=self.alpha.dtype)
        linear = {"linear_a0": self._linear[0].clone() if self._linear is not None else empty,
                  "linear_prev": self._prev_alpha.clone() if self._prev_alpha is not None else empty,
                  "linear_step": torch.tensor(self._step, dtype=torch.float64)}
        size = {"size_centre": self.size_centre.clone()} if self.fits_size else {}
        return {**super().state_dict(), "p_ref": self.p_ref.clone(), **linear, **size}

    def load_state_dict(self, state: dict) -> None:
        self.p_ref = state["p_ref"].clone()
        if ("log_size" in state) != self.fits_size:
            raise ValueError("the checkpoint's shape set was made " + ("with" if "log_size" in state else "without")
                             + " a fitted size, this run's " + ("with" if self.fits_size else "without"))
        if self.fits_size:
            self.size_centre = state["size_centre"].clone()
        if ("log_length" in state) != self.fits_length:
            raise ValueError("the checkpoint's shape set was made " + ("with" if "log_length" in state else "without")
                             + " a fitted length, this run's " + ("with" if self.fits_length else "without"))
        if ("residual" in state) != self.has_residual:
            raise ValueError("the checkpoint's shape set was made " + ("with" if "residual" in state else "without")
                             + " a residual deformation, this run's " + ("with" if self.has_residual else "without"))
        if self.has_residual and tuple(state["residual"].shape) != tuple(self.params["residual"].shape):
            raise ValueError(f"the checkpoint's residual has {tuple(state['residual'].shape)} coefficients, this "
                             f"run's {tuple(self.params['residual'].shape)} (another residual_points)")
        self._at_ref = self._linear = self._prev_alpha = None
        self._step = 0.0
        for k in self.params:
            self.params[k] = state[k].detach().clone().requires_grad_(True)
        self.last_u = None
        if "linear_step" in state:  # checkpoints from before the linearisation have none
            self._step = float(state["linear_step"])
            if state["linear_prev"].numel():
                self._prev_alpha = state["linear_prev"].clone()
            if state["linear_a0"].numel() and self.LINEAR_TOL is not None:
                self._linear = self._linearise(state["linear_a0"].clone())
