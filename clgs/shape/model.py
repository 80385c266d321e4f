"""Statistical shape model of stationary velocity fields (SVF), and the density atlas.

A model lives on a regular grid over the template (``shape`` (Z, Y, X), ``spacing`` and ``origin``
(Z, Y, X) in mm, origin = centre of voxel [0, 0, 0]); points and vector components are (x, y, z)
in mm, as everywhere in clgs. Mapping to the [-1, 1]^3 scene is the caller's job.

    v(alpha) = v_mean + sum_m alpha_m sigma_m phi_m           alpha ~ N(0, I)
    phi = exp(v)  (template -> subject),   u = phi - id

``exp`` is scaling and squaring: ``u_0 = v / 2^N`` then ``u_{k+1}(x) = u_k(x) + u_k(x + u_k(x))``.
N is chosen from the largest velocity so that the first step moves every point by less than half
a grid cell (and at least ``MIN_SQUARINGS``), so even stiff fields give fold-free maps.

Outside the grid a displacement is CLAMPED: it takes the value at the nearest border voxel
(``grid_sample`` with ``padding_mode="border"``). This keeps the map continuous (zero padding
would tear it at the box wall and can fold it there during squaring); models are built on a box
with a margin around the bone, where the velocities are small.

One model file is ONE npz (``np.load(..., allow_pickle=False)``) holding the velocity model, the
optional density atlas, and a JSON metadata record (format name and version, population ids,
settings and their hash, variance kept, registration residuals).
"""
from __future__ import annotations

import json
import math
import zipfile

import numpy as np
import torch
import torch.nn.functional as F

from clgs.errors import ClgsError, InputError
from clgs.geometry import Grid
from clgs.ops.field_sampler import sample
from clgs.shape.template import json_array, json_from_array, save_npz_atomic, zyx_triple

MODEL_FORMAT = "clgs.shape_model"
MODEL_VERSION = 1
# what a damaged or foreign npz raises on reading (truncated zip, object arrays, bad JSON, short data)
_UNREADABLE = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, json.JSONDecodeError)
MIN_SQUARINGS = 4
MAX_SQUARINGS = 40


class ModelFileError(ClgsError, ValueError):
    """A model file that is missing, of another format or version, or internally inconsistent."""


# --------------------------------------------------------------------------------------- fields
def _norm_scale(shape, spacing, like: torch.Tensor) -> torch.Tensor:
    """Per component (x, y, z): mm -> grid_sample's normalised units (align_corners=True)."""
    Z, Y, X = shape
    dz, dy, dx = spacing
    ext = [(X - 1) * dx, (Y - 1) * dy, (Z - 1) * dz]
    if min(ext) <= 0:
        raise InputError(f"a field grid needs at least 2 voxels per axis, got {tuple(shape)}")
    return torch.tensor([2.0 / e for e in ext], dtype=like.dtype, device=like.device)


def _identity_grid(shape, like: torch.Tensor) -> torch.Tensor:
    """Voxel centres in normalised coordinates, (Z, Y, X, 3) as (x, y, z)."""
    axes = [torch.linspace(-1.0, 1.0, n, dtype=like.dtype, device=like.device) for n in shape]
    z, y, x = torch.meshgrid(*axes, indexing="ij")
    return torch.stack([x, y, z], -1)


def _sample_norm(field: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """field (C, Z, Y, X) at normalised points grid (..., 3) -> (..., C); clamped outside."""
    lead = grid.shape[:-1]
    g = grid.reshape(1, 1, 1, -1, 3)
    out = F.grid_sample(field.unsqueeze(0), g, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(field.shape[0], -1).transpose(0, 1).reshape(*lead, field.shape[0])


def sample_field(field: torch.Tensor, points: torch.Tensor, spacing, origin, sampler=None) -> torch.Tensor:
    """Trilinear samples (N, C) of a (C, Z, Y, X) field at points (N, 3) (x, y, z mm).

    Differentiable in the field and in the points. Outside the grid: clamped to the border.
    ``sampler``: a :class:`clgs.ops.field_sampler.FieldSampler` computes it in OpenCL (same values to
    rounding); None uses torch's ``grid_sample``."""
    shape = tuple(field.shape[1:])
    origin_xyz = torch.tensor(zyx_triple("origin", origin)[::-1], dtype=field.dtype, device=field.device)
    points = torch.as_tensor(points, dtype=field.dtype, device=field.device)
    if sampler is not None:
        dz, dy, dx = zyx_triple("spacing", spacing)
        step = torch.tensor([dx, dy, dz], dtype=field.dtype)
        return sample(field, ((points - origin_xyz) / step).T.contiguous(), sampler).T
    scale = _norm_scale(shape, zyx_triple("spacing", spacing), field)
    return _sample_norm(field, (points - origin_xyz) * scale - 1.0)


def squarings_for(v: torch.Tensor, spacing, min_squarings: int = MIN_SQUARINGS) -> int:
    """Number N of squarings so that |v| / 2^N < half a grid cell along every axis."""
    dz, dy, dx = zyx_triple("spacing", spacing)
    with torch.no_grad():
        d = torch.tensor([dx, dy, dz], dtype=v.dtype, device=v.device).view(3, 1, 1, 1)
        cells = float((v.detach().abs() / d).max()) if v.numel() else 0.0
    if not math.isfinite(cells):
        raise InputError("velocity field contains NaN or Inf")
    n = math.ceil(math.log2(cells / 0.5)) if cells > 0.5 else 0
    n = max(n + 1 if cells / 2.0 ** n >= 0.5 else n, min_squarings)
    if n > MAX_SQUARINGS:
        raise InputError(f"velocity field too large ({cells:.3g} cells): more than {MAX_SQUARINGS} squarings")
    return n


def exp_velocity(v: torch.Tensor, spacing, n_squarings: int | None = None,
                 min_squarings: int = MIN_SQUARINGS, sampler=None) -> torch.Tensor:
    """Displacement u = exp(v) - id (3, Z, Y, X) in mm of a stationary velocity field v (3, Z, Y, X)
    in mm (components x, y, z), by scaling and squaring. Differentiable in v. ``sampler``: as
    :func:`sample_field` (the squarings then run in voxel units, in OpenCL)."""
    if v.dim() != 4 or v.shape[0] != 3:
        raise InputError(f"velocity must be (3, Z, Y, X), got {tuple(v.shape)}")
    shape = tuple(v.shape[1:])
    if n_squarings is None:
        n_squarings = squarings_for(v, spacing, min_squarings)
    if sampler is not None:
        return _exp_in_voxels(v, spacing, n_squarings, sampler)
    scale = _norm_scale(shape, zyx_triple("spacing", spacing), v).view(3, 1, 1, 1)
    ident = _identity_grid(shape, v)
    u = v * (scale / (2.0 ** n_squarings))  # normalised units
    for _ in range(n_squarings):
        moved = ident + u.permute(1, 2, 3, 0)
        u = u + _sample_norm(u, moved).permute(3, 0, 1, 2)
    return u / scale


def _exp_in_voxels(v: torch.Tensor, spacing, n_squarings: int, sampler) -> torch.Tensor:
    dz, dy, dx = zyx_triple("spacing", spacing)
    step = torch.tensor([dx, dy, dz], dtype=v.dtype).view(3, 1, 1, 1)
    axes = [torch.arange(n, dtype=v.dtype) for n in v.shape[1:]]
    k, j, i = torch.meshgrid(*axes, indexing="ij")
    ident = torch.stack([i, j, k]).reshape(3, -1)
    u = v / (step * 2.0 ** n_squarings)  # voxels
    for _ in range(n_squarings):
        u = u + sample(u, ident + u.reshape(3, -1), sampler).reshape(u.shape)
    return u * step


def jacobian_determinant(u, spacing) -> np.ndarray:
    """det(I + grad u) (Z, Y, X) of the map x -> x + u(x); u (3, Z, Y, X) mm, central differences.

    Values <= 0 mark folding."""
    u = u.detach().cpu().numpy() if isinstance(u, torch.Tensor) else np.asarray(u)
    u = u.astype(np.float64)
    dz, dy, dx = zyx_triple("spacing", spacing)
    J = np.empty(u.shape[1:] + (3, 3))
    for c in range(3):
        gz, gy, gx = np.gradient(u[c], dz, dy, dx)
        J[..., c, 0], J[..., c, 1], J[..., c, 2] = gx, gy, gz
    J += np.eye(3)
    return np.linalg.det(J).astype(np.float32)


# --------------------------------------------------------------------------------------- model
class ShapeModel:
    """PCA of stationary velocity fields on a grid over the template.

    mean (3, Z, Y, X) mm; modes (M, 3, Z, Y, X), orthonormal as flat vectors; sigma (M,) the
    standard deviation of each mode's score; spacing/origin (Z, Y, X) mm. ``meta`` carries the
    file's metadata (population, settings, variance kept, residuals). ``beyond_cov`` (6, Z, Y, X)
    mm^2 or None: the covariance (xx, yy, zz, xy, xz, yz) of what a left-out subject's field keeps
    beyond the kept modes (:func:`clgs.shape.builder.beyond_span_covariance`), for the shape
    surface's uncertainty."""

    def __init__(self, mean, modes, sigma, spacing, origin, meta: dict | None = None,
                 dtype=torch.float32, beyond_cov=None):
        mean = torch.as_tensor(np.asarray(mean) if not isinstance(mean, torch.Tensor) else mean, dtype=dtype)
        modes = torch.as_tensor(np.asarray(modes) if not isinstance(modes, torch.Tensor) else modes, dtype=dtype)
        sigma = torch.as_tensor(np.asarray(sigma) if not isinstance(sigma, torch.Tensor) else sigma, dtype=dtype)
        if mean.dim() != 4 or mean.shape[0] != 3 or min(mean.shape[1:]) < 2:
            raise ModelFileError(f"velocity mean must be (3, Z, Y, X) with Z, Y, X >= 2, got {tuple(mean.shape)}")
        if modes.dim() != 5 or tuple(modes.shape[1:]) != tuple(mean.shape):
            raise ModelFileError(f"modes must be (M, {', '.join(map(str, mean.shape))}), got {tuple(modes.shape)}")
        if sigma.shape != (modes.shape[0],):
            raise ModelFileError(f"sigma must have one entry per mode ({modes.shape[0]}), got {tuple(sigma.shape)}")
        if not (torch.isfinite(mean).all() and torch.isfinite(modes).all() and torch.isfinite(sigma).all()):
            raise ModelFileError("shape model contains NaN or Inf")
        if (sigma < 0).any():
            raise ModelFileError("mode standard deviations (sigma) must be >= 0")
        self.mean, self.modes, self.sigma = mean, modes, sigma
        self.spacing = zyx_triple("spacing", spacing)
        self.origin = zyx_triple("origin", origin)
        if min(self.spacing) <= 0:
            raise ModelFileError(f"grid spacing must be positive, got {self.spacing}")
        self.meta = dict(meta or {})
        self.beyond_cov = None
        if beyond_cov is not None:
            cov = np.asarray(beyond_cov, np.float32)
            if cov.shape != (6,) + tuple(mean.shape[1:]) or not np.isfinite(cov).all() or cov[:3].min() < 0:
                grid = ", ".join(map(str, mean.shape[1:]))
                raise ModelFileError(f"the beyond-span covariance must be finite (6, {grid}) with variances >= 0, "
                                     f"got {cov.shape}")
            self.beyond_cov = cov

    # ---- sizes
    @property
    def n_modes(self) -> int:
        return int(self.modes.shape[0])

    @property
    def shape(self) -> tuple:
        return tuple(int(s) for s in self.mean.shape[1:])

    @property
    def dtype(self):
        return self.mean.dtype

    def to(self, dtype) -> ShapeModel:
        """A copy in another float dtype (float64 for gradient checks)."""
        return ShapeModel(self.mean.to(dtype), self.modes.to(dtype), self.sigma.to(dtype), self.spacing,
                          self.origin, self.meta, dtype=dtype, beyond_cov=self.beyond_cov)

    def grid(self):
        return Grid(self.shape, tuple(self.origin[::-1]), tuple(self.spacing[::-1]))

    # ---- fields
    def _alpha(self, alpha) -> torch.Tensor:
        if alpha is None:
            return torch.zeros(self.n_modes, dtype=self.dtype)
        alpha = torch.as_tensor(alpha, dtype=self.dtype)
        if alpha.shape != (self.n_modes,):
            raise InputError(f"alpha must have {self.n_modes} entries (one per mode), got {tuple(alpha.shape)}")
        return alpha

    def velocity(self, alpha=None) -> torch.Tensor:
        """v(alpha) (3, Z, Y, X) mm; differentiable in alpha."""
        a = self._alpha(alpha) * self.sigma
        return self.mean + torch.tensordot(a, self.modes, dims=1)

    def displacement(self, alpha=None, n_squarings: int | None = None, inverse: bool = False) -> torch.Tensor:
        """u = exp(v(alpha)) - id (3, Z, Y, X) mm; with ``inverse`` exp(-v) - id (subject -> template)."""
        v = self.velocity(alpha)
        return exp_velocity(-v if inverse else v, self.spacing, n_squarings)

    def sample(self, u: torch.Tensor, points, sampler=None) -> torch.Tensor:
        """A field u (3, Z, Y, X) at points (N, 3) (x, y, z mm) -> (N, 3); clamped outside the grid."""
        return sample_field(u, points, self.spacing, self.origin, sampler)

    def jacobian_determinant(self, alpha=None, u=None) -> np.ndarray:
        """det of the map's Jacobian on the grid (Z, Y, X); <= 0 means folding."""
        if u is None:
            with torch.no_grad():
                u = self.displacement(alpha)
        return jacobian_determinant(u, self.spacing)

    def project(self, v) -> torch.Tensor:
        """Scores alpha (M,) of a velocity field v (3, Z, Y, X) (least squares on the modes)."""
        v = torch.as_tensor(v, dtype=self.dtype)
        flat = self.modes.reshape(self.n_modes, -1)
        coef = flat @ (v - self.mean).reshape(-1)
        safe = torch.where(self.sigma > 0, self.sigma, torch.ones_like(self.sigma))
        return torch.where(self.sigma > 0, coef / safe, torch.zeros_like(coef))

    # ---- files
    def save(self, path, atlas: DensityAtlas | None = None, meta: dict | None = None) -> None:
        save_model(path, self, atlas, meta)

    @classmethod
    def load(cls, path) -> ShapeModel:
        return load_model(path)[0]


class DensityAtlas:
    """Per-voxel mean and variance of the population's CT in template space.

    mean, var: (Z, Y, X) float32 (attenuation units of the CT, e.g. per mm); spacing/origin
    (Z, Y, X) mm. Outside the grid both are 0 (air, and no uncertainty)."""

    def __init__(self, mean, var, spacing, origin, meta: dict | None = None):
        mean = np.asarray(mean, np.float32)
        var = np.asarray(var, np.float32)
        if mean.ndim != 3 or var.shape != mean.shape or min(mean.shape) < 2:
            raise ModelFileError(f"atlas mean {mean.shape} and variance {var.shape} must be the same (Z, Y, X) "
                                 "shape, at least 2 voxels per axis")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var))):
            raise ModelFileError("density atlas contains NaN or Inf")
        if var.min() < 0:
            raise ModelFileError("density atlas variance must be >= 0")
        self.mean, self.var = mean, var
        self.spacing = zyx_triple("spacing", spacing)
        self.origin = zyx_triple("origin", origin)
        self.meta = dict(meta or {})
        self._torch = {}

    @property
    def shape(self) -> tuple:
        return tuple(int(s) for s in self.mean.shape)

    def grid(self):
        return Grid(self.shape, tuple(self.origin[::-1]), tuple(self.spacing[::-1]))

    def sample(self, points, which: str = "mean"):
        """``which`` ("mean" or "var") at points (N, 3) mm, trilinear, 0 outside the grid.

        Torch points give a torch result (differentiable in the points); NumPy gives NumPy."""
        if which not in ("mean", "var"):
            raise InputError(f"which must be 'mean' or 'var', got {which!r}")
        is_torch = isinstance(points, torch.Tensor)
        pts = points if is_torch else torch.as_tensor(np.asarray(points, np.float64), dtype=torch.float64)
        key = (which, pts.dtype)
        if key not in self._torch:
            self._torch[key] = torch.as_tensor(getattr(self, which), dtype=pts.dtype)[None]
        vol = self._torch[key]
        origin_xyz = torch.tensor(self.origin[::-1], dtype=pts.dtype)
        scale = _norm_scale(self.shape, self.spacing, vol)
        g = ((pts - origin_xyz) * scale - 1.0).reshape(1, 1, 1, -1, 3)
        out = F.grid_sample(vol.unsqueeze(0), g, mode="bilinear", padding_mode="zeros", align_corners=True)
        out = out.reshape(pts.shape[:-1])
        return out if is_torch else out.numpy().astype(np.float32)

    def mean_at(self, points):
        return self.sample(points, "mean")

    def mean_var_at(self, points: torch.Tensor):
        """(mean, var) at torch points (N, 3) mm from one trilinear pass over both volumes: the
        same bits as :meth:`mean_at` and :meth:`var_at` (grid_sample weighs each channel alike),
        for half the cost (the density prior asks for both every iteration)."""
        key = ("mean+var", points.dtype)
        if key not in self._torch:
            self._torch[key] = torch.as_tensor(np.stack([self.mean, self.var]), dtype=points.dtype)
        vol = self._torch[key]
        origin_xyz = torch.tensor(self.origin[::-1], dtype=points.dtype)
        scale = _norm_scale(self.shape, self.spacing, vol)
        g = ((points - origin_xyz) * scale - 1.0).reshape(1, 1, 1, -1, 3)
        out = F.grid_sample(vol.unsqueeze(0), g, mode="bilinear", padding_mode="zeros", align_corners=True)
        out = out.reshape(2, *points.shape[:-1])
        return out[0], out[1]

    def var_at(self, points):
        return self.sample(points, "var")

    def save(self, path, meta: dict | None = None) -> None:
        save_model(path, None, self, meta)

    @classmethod
    def load(cls, path) -> DensityAtlas:
        atlas = load_model(path, need_shape_model=False)[1]
        if atlas is None:
            raise ModelFileError(f"{path} holds no density atlas (the population had no CT volumes)")
        return atlas


# --------------------------------------------------------------------------------------- files
def save_model(path, shape_model: ShapeModel | None, atlas: DensityAtlas | None = None,
               meta: dict | None = None) -> None:
    """Write a shape model and/or density atlas as one versioned npz, atomically.

    ``meta`` (JSON-serialisable) is stored with the format name and version; keys used by clgs:
    population (ids), settings, settings_hash, variance_kept, residuals."""
    if shape_model is None and atlas is None:
        raise InputError("nothing to save: give a shape model, an atlas or both")
    record = dict(shape_model.meta if shape_model is not None else {})
    record.update(meta or {})
    record.update(format=MODEL_FORMAT, version=MODEL_VERSION, has_shape_model=shape_model is not None,
                  has_atlas=atlas is not None)
    arrays = {}
    if shape_model is not None:
        record["n_modes"] = shape_model.n_modes
        record["grid_shape"] = list(shape_model.shape)
        arrays.update(velocity_mean=shape_model.mean.detach().cpu().numpy().astype(np.float32),
                      modes=shape_model.modes.detach().cpu().numpy().astype(np.float32),
                      sigma=shape_model.sigma.detach().cpu().numpy().astype(np.float32),
                      spacing=np.asarray(shape_model.spacing), origin=np.asarray(shape_model.origin))
        if shape_model.beyond_cov is not None:
            arrays["beyond_cov"] = shape_model.beyond_cov
    if atlas is not None:
        record["atlas_shape"] = list(atlas.shape)
        arrays.update(atlas_mean=atlas.mean, atlas_var=atlas.var, atlas_spacing=np.asarray(atlas.spacing),
                      atlas_origin=np.asarray(atlas.origin))
    arrays["metadata"] = json_array(record)
    save_npz_atomic(path, arrays)


def read_metadata(path) -> dict:
    """The metadata record of a model file without loading its arrays."""
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ModelFileError(f"{path} is not a clgs model file (not an npz archive)")
        with z:
            if "metadata" not in z.files:
                raise ModelFileError(f"{path} is not a clgs model file (no metadata record)")
            meta = json_from_array(z["metadata"])
    except FileNotFoundError:
        raise ModelFileError(f"model file {path} does not exist: build it first (clgs <anatomy> build-model)") from None
    except ModelFileError:
        raise
    except _UNREADABLE as exc:
        raise ModelFileError(f"cannot read model file {path} ({exc}): rebuild it (clgs <anatomy> build-model "
                             "--force) or download it again") from exc
    if meta.get("format") != MODEL_FORMAT:
        raise ModelFileError(f"{path} is not a clgs shape model (format {meta.get('format')!r})")
    version = meta.get("version")
    if not isinstance(version, int) or version < 1 or version > MODEL_VERSION:
        raise ModelFileError(f"{path} has model format version {version!r}; this clgs reads versions 1..{MODEL_VERSION}"
                             + (": upgrade clgs" if isinstance(version, int) and version > MODEL_VERSION else ""))
    return meta


def load_model(path, need_shape_model: bool = True):
    """(ShapeModel or None, DensityAtlas or None) from one model file; shapes and version checked."""
    meta = read_metadata(path)
    try:
        return _load_arrays(path, meta, need_shape_model)
    except ModelFileError:
        raise
    except _UNREADABLE as exc:
        raise ModelFileError(f"cannot read model file {path} ({exc}): rebuild it (clgs <anatomy> build-model "
                             "--force) or download it again") from exc


def _load_arrays(path, meta: dict, need_shape_model: bool):
    with np.load(path, allow_pickle=False) as z:
        files = set(z.files)
        sm = atlas = None
        if meta.get("has_shape_model"):
            need = {"velocity_mean", "modes", "sigma", "spacing", "origin"}
            if not need <= files:
                raise ModelFileError(f"{path}: shape model arrays missing: {sorted(need - files)}")
            sm = ShapeModel(z["velocity_mean"], z["modes"], z["sigma"], tuple(z["spacing"]), tuple(z["origin"]),
                            meta=meta, beyond_cov=z["beyond_cov"] if "beyond_cov" in files else None)
            same_grid = list(sm.shape) == list(meta.get("grid_shape", sm.shape))
            if not same_grid or sm.n_modes != meta.get("n_modes", sm.n_modes):
                raise ModelFileError(f"{path}: arrays do not match the metadata (grid {sm.shape} vs "
                                     f"{meta.get('grid_shape')}, modes {sm.n_modes} vs {meta.get('n_modes')})")
        elif need_shape_model:
            raise ModelFileError(f"{path} holds no shape model")
        if meta.get("has_atlas"):
            need = {"atlas_mean", "atlas_var", "atlas_spacing", "atlas_origin"}
            if not need <= files:
                raise ModelFileError(f"{path}: atlas arrays missing: {sorted(need - files)}")
            atlas = DensityAtlas(z["atlas_mean"], z["atlas_var"], tuple(z["atlas_spacing"]),
                                 tuple(z["atlas_origin"]), meta=meta)
            if list(atlas.shape) != list(meta.get("atlas_shape", atlas.shape)):
                raise ModelFileError(f"{path}: atlas arrays do not match the metadata (grid {atlas.shape} vs "
                                     f"{meta.get('atlas_shape')})")
    return sm, atlas
