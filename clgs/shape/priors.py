"""The loss terms a shape model and a density atlas give a Gaussian fit: the shape prior on the
mode coefficients and the atlas density prior on the field, over a random sub-grid."""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from clgs.errors import InputError
from clgs.geometry import Grid
from clgs.shape.gaussian_set import ShapeGuidedSet


def shape_prior_term(set_name: str = "shape"):
    """|alpha|^2 of the shape set."""

    def fn(ctx):
        s = _set(ctx.trainer, set_name)
        return (s.alpha * s.alpha).sum()

    return fn


def residual_prior_term(bending: float, bending_start: float, steps: int, set_name: str = "shape"):
    """The residual's prior (:meth:`clgs.shape.residual.ResidualGrid.prior`) with its bending
    weight scheduled: ``bending_start`` times ``bending`` at the first iteration, decaying
    log-linearly to ``bending`` over ``steps`` iterations (stiff first, so the residual takes the
    coarse shape difference before the local one)."""
    start = max(float(bending_start), 1e-12)

    def fn(ctx):
        t = min(max(ctx.iteration / max(int(steps), 1), 0.0), 1.0)
        return _set(ctx.trainer, set_name).residual_prior(float(bending) * start ** (1.0 - t))

    return fn


def _set(trainer, name):
    for s in trainer.sets:
        if s.name == name:
            return s
    raise KeyError(name)


def random_subgrid(grid, n: int, generator: torch.Generator):
    """An ``n^3`` strided grid spanning ``grid``'s box with a random sub-stride offset."""
    shape = np.asarray(grid.shape)  # (Z, Y, X)
    sp = np.asarray(grid.spacing, float)  # (x, y, z)
    counts = np.minimum(shape, n)
    extent = (shape[::-1] - 1) * sp  # (x, y, z)
    step = np.where(counts[::-1] > 1, extent / np.maximum(counts[::-1], 1), 0.0)
    offset = torch.rand(3, generator=generator, dtype=torch.float64).numpy() * step
    origin = np.asarray(grid.origin, float) + offset
    return Grid(tuple(int(c) for c in counts), tuple(origin), tuple(np.where(step > 0, step, sp)))


class DensityPrior:
    """``L_density`` of the module doc, evaluated lazily per iteration.

    ``field="shape"``: the shape set's field ``V_s`` inside the template's bone (carried by the
    current deformation), as the paper writes it. ``field="all"``: the whole model's field
    everywhere on the sub-grid, against the atlas of the whole scan (bone and the tissue around
    it), with the same confidence ``w``; the free Gaussians then get the atlas's help where the
    few views leave them undetermined (docs/methods.md)."""

    def __init__(self, atlas, template, geometry, value_scale: float, s: float, n_points: int,
                 set_name: str = "shape", field: str = "shape", factors: tuple = (1.0, 1.0), limb=None):
        if field not in ("shape", "all"):
            raise InputError(f"density prior field must be 'shape' or 'all', got {field!r}")
        self.atlas, self.template, self.geometry = atlas, template, geometry
        self.value_scale = float(value_scale)
        self.s2 = float(s) ** 2
        self.n_points = int(n_points)
        self.set_name = set_name
        self.field = field
        # the atlas scaled to the scan (clgs.shape.calibration): inside the template's bone by the
        # first, outside it by the second
        self.factors = (float(factors[0]), float(factors[1]))
        self._split: tuple | None = None  # split_atlas's two parts, made on first use
        # the atlas's tissue carried onto the scan's limb outline (clgs.shape.limb.LimbWarp; None:
        # the atlas's own limb), placed for the set's size and length (cached by them)
        self.limb = limb
        self._placed: tuple = (None, None)
        self._sdf: torch.Tensor | None = None  # the template's signed distance, for the carry's blend
        lo, hi = template.bounds()
        self._lo, self._hi = torch.as_tensor(lo, dtype=torch.float32), torch.as_tensor(hi, dtype=torch.float32)
        self._label = torch.as_tensor(template.label.astype(np.float32))[None, None]

    def _inside_template(self, pts_mm: torch.Tensor) -> torch.Tensor:
        g = ((pts_mm - self._lo) / (self._hi - self._lo) * 2 - 1).reshape(1, 1, 1, -1, 3)
        m = F.grid_sample(self._label, g, mode="bilinear", padding_mode="zeros", align_corners=True)
        return m.reshape(-1)

    def _inside_atlas(self, pts_mm: torch.Tensor) -> torch.Tensor:
        origin = torch.as_tensor(np.asarray(self.atlas.origin[::-1], float), dtype=pts_mm.dtype)
        extent = torch.as_tensor((np.asarray(self.atlas.shape[::-1]) - 1) * np.asarray(self.atlas.spacing[::-1], float),
                                 dtype=pts_mm.dtype)
        rel = pts_mm - origin
        return ((rel >= 0) & (rel <= extent)).all(dim=-1).to(pts_mm.dtype)

    def _sized_atlas(self, s, pts_mm, x_bone):
        """The atlas for a bone fitted at another size ``s`` than the model's: (mean, var, the
        points read, a 0/1 mask of the points held), read where :meth:`_sized_points` says."""
        at, keep = self._sized_points(s, pts_mm, x_bone)
        mean, var = self._atlas_at(at.double())
        return mean, var, at, keep

    def _sized_points(self, s, pts_mm, x_bone):
        """(the template points to read, a 0/1 mask of the points held) for a bone fitted at
        another size ``s`` than the model's. The bone takes the size (the atlas read at ``x_bone``,
        the similarity undone); the tissue around it takes a larger size but not a smaller one (a
        limb has a girth of its own beside its bone's). Points outside the scaled bone that the
        tissue's read would place inside the template's bone (a ring around a smaller bone) are
        not held (why: docs/methods.md, "The bone's size")."""
        if s.size >= 1.0:  # the tissue takes the bone's size: one read, every point held
            return x_bone, torch.ones(len(pts_mm), dtype=pts_mm.dtype)
        x_tissue = s.to_template(pts_mm, tissue=True)
        in_bone = self._inside_template(x_bone) > 0.5
        in_tissue_read = self._inside_template(x_tissue) > 0.5
        at = torch.where(in_bone[:, None], x_bone, x_tissue)
        return at, (in_bone | ~in_tissue_read).to(pts_mm.dtype)

    def _atlas_at(self, x_t: torch.Tensor):
        """The atlas's mean and variance at template points, from one trilinear pass."""
        return self.atlas.mean_var_at(x_t)

    def _points_mm(self, grid) -> torch.Tensor:
        """A scene-unit grid's points in mm (world), (N, 3) float32."""
        pts = torch.as_tensor(grid.points().reshape(-1, 3), dtype=torch.float32)
        return pts / self.geometry.scale + torch.as_tensor(self.geometry.centre_xyz, dtype=torch.float32)

    def _points(self, s, pts_mm: torch.Tensor):
        """(the template points the atlas is read at, a 0/1 mask of the points held or None) for
        points of the subject (mm), carried to the template by the set ``s`` (its fitted size as
        :meth:`_sized_points` places them, with ``field="all"``)."""
        x_t = s.to_template(pts_mm) if isinstance(s, ShapeGuidedSet) else pts_mm
        if isinstance(s, ShapeGuidedSet) and s.fits_size and self.field == "all":
            return self._sized_points(s, pts_mm, x_t)
        return x_t, None

    @property
    def _carries(self) -> bool:
        """Whether reads are carried onto the scan's limb (a warp, and the whole field held)."""
        return self.limb is not None and self.field == "all"

    def _carried(self, s, pts_mm: torch.Tensor, x_t: torch.Tensor):
        """(the template points read once points of the subject are carried onto the atlas's limb,
        the weight of the carry (N,) float64) by ``limb`` (:class:`clgs.shape.limb.LimbWarp`), from
        the plain read ``x_t`` of :meth:`_points`: the carry's blend from the template bone's
        distance at ``x_t``, and the read moved by the carry over the tissue's size across the leg
        (the size where larger than 1, as :meth:`_sized_points` reads the tissue; the map to the
        template is taken as that scaling where the carry acts, 5 mm and more from the bone). The
        atlas's outline is placed for the set's size and length (cached by them)."""
        from clgs.shape.limb import LEG_AXIS, blend_of_distance

        fitted = isinstance(s, ShapeGuidedSet) and s.fits_size
        key = (s.size, s.length, tuple(s.size_centre.tolist())) if fitted else None
        across = max(s.size, 1.0) if fitted else 1.0
        if self._placed[0] != key or self._placed[1] is None:
            along = across * max(s.length, 1.0) if fitted else 1.0
            centre = s.size_centre.numpy() if fitted else np.zeros(3)
            self._placed = (key, self.limb.placed(centre, across, along))
        if self._sdf is None:
            self._sdf = torch.as_tensor(self.template.sdf.astype(np.float32))[None, None]
        g = ((x_t.float() - self._lo) / (self._hi - self._lo) * 2 - 1).reshape(1, 1, 1, -1, 3)
        d = F.grid_sample(self._sdf, g, mode="bilinear", padding_mode="border", align_corners=True).reshape(-1)
        # beyond the template's grid: its border's distance plus the way out to the point (as sdf_at)
        out = torch.clamp(torch.maximum(self._lo - x_t.float(), x_t.float() - self._hi), min=0.0)
        d = d + torch.linalg.norm(out, dim=1)
        blend = blend_of_distance(d.double().numpy())
        p = pts_mm.detach().double().numpy()
        moved, weight = self.limb.to_atlas(self._placed[1], p, blend)
        shift = torch.as_tensor((moved - p) / across, dtype=x_t.dtype)
        shift[:, LEG_AXIS] = 0.0
        return x_t + shift, torch.as_tensor(weight, dtype=torch.float64)

    def _read(self, s, pts_mm: torch.Tensor):
        """(mean, var, the template points read, the mask of :meth:`_points`) of the atlas at
        points of the subject (mm), scaled by ``factors`` (one read of the atlas, or of its two
        parts when they are scaled apart). With ``limb``, the points are carried onto the atlas's
        limb first and, as far as they are carried, the atlas's variance there is at most its
        variance inside the limb (the population's spread of limb edges is not this scan's
        uncertainty once its edge is measured: clgs.shape.limb)."""
        x_t, keep = self._points(s, pts_mm)
        carried = None
        if self._carries:
            x_t, carried = self._carried(s, pts_mm, x_t)
        if self.factors == (1.0, 1.0):
            mean, var = self._atlas_at(x_t.double())
        else:
            (bm, bv), (rm, rv) = (a.mean_var_at(x_t.double()) for a in self.split_atlas())
            b, t = self.factors
            mean, var = b * bm + t * rm, b * b * bv + t * t * rv
        if carried is not None:
            cap = self.limb.variance * self.factors[1] ** 2
            var = var * (1.0 - carried) + carried * torch.clamp(var, max=cap)
        return mean, var, x_t, keep

    def split_atlas(self) -> tuple:
        """(the atlas inside the template's bone, the atlas outside it): two atlases on the atlas's
        grid whose sum is the atlas (split at its voxels, so that each read, trilinear, is the
        atlas's read in two parts); what the factors scale."""
        if self._split is None:
            from clgs.shape.model import DensityAtlas

            a, tpl = self.atlas, self.template
            if (a.shape == tuple(tpl.label.shape) and np.allclose(a.spacing, tpl.spacing)
                    and np.allclose(a.origin, tpl.origin)):
                label = np.asarray(tpl.label, np.float32)
            else:
                pts = torch.as_tensor(a.grid().points().reshape(-1, 3), dtype=torch.float32)
                label = (self._inside_template(pts) > 0.5).numpy().reshape(a.shape).astype(np.float32)
            self._split = tuple(DensityAtlas(a.mean * m, a.var * m, a.spacing, a.origin)
                                for m in (label, 1.0 - label))
        return self._split

    def atlas_parts(self, shape_set, grid, chunk: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
        """The atlas's mean as this prior reads it for ``shape_set``'s fit, on ``grid`` (scene
        units), split into the template bone's part and the rest's: two (Z, Y, X) float32 volumes
        in the atlas's units, unscaled (what :mod:`clgs.shape.calibration` projects)."""
        pts_mm = self._points_mm(grid)
        bone = np.empty(len(pts_mm), np.float32)
        rest = np.empty(len(pts_mm), np.float32)
        inside, outside = self.split_atlas()
        with torch.no_grad():
            for i in range(0, len(pts_mm), chunk):
                x_t, _ = self._points(shape_set, pts_mm[i:i + chunk])
                if self._carries:
                    x_t = self._carried(shape_set, pts_mm[i:i + chunk], x_t)[0]
                bone[i:i + chunk] = inside.mean_at(x_t.double()).numpy()
                rest[i:i + chunk] = outside.mean_at(x_t.double()).numpy()
        shape = tuple(grid.shape)
        return bone.reshape(shape), rest.reshape(shape)

    def __call__(self, ctx):
        trainer = ctx.trainer
        s = _set(trainer, self.set_name)
        grid = random_subgrid(self.geometry.volume_grid(scene=True), self.n_points, ctx.generator)
        if self.field == "all":
            tensors = ctx.tensors
        else:
            n = len(s)
            offset = 0
            for other in trainer.sets:  # the shape set's rows within the concatenated scene tensors
                if other is s:
                    break
                offset += len(other)
            tensors = tuple(t[offset:offset + n] for t in ctx.tensors)
        v = ctx.voxelize(grid, tensors).reshape(-1)
        with torch.no_grad():
            pts_mm = self._points_mm(grid)
            mean, var, x_t, keep = self._read(s, pts_mm)
            mean = mean.float() * self.value_scale
            var = var.float() * self.value_scale ** 2
            w = torch.exp(-var / self.s2)
            if keep is not None:
                w = w * keep
            # the atlas says nothing beyond its grid (the template's): where a larger scan (a longer
            # bone) reaches past it, the field is left to the projections, not pulled to the zeros
            # the atlas reads there (tested on the scan's points: on the atlas's own grid every
            # point is inside)
            # (with a fitted size the atlas is read at x_t, in the model's frame and size: that is
            # the point tested)
            fitted = isinstance(s, ShapeGuidedSet) and s.fits_size
            w = w * self._inside_atlas(x_t if fitted else pts_mm)
            if self.field == "shape":
                w = w * self._inside_template(x_t)
        return (w * (v - mean) ** 2).mean()


# ---------------------------------------------------------------------- building a run
