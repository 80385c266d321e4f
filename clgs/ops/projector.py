"""Gaussian X-ray projector: line integrals of a sum of 3D Gaussians, as a torch autograd op.

``project(means, scales, quats, densities, geometry, views, mode)`` returns the projections
(len(views), V, U) in mm-based units: the scene-unit line integral divided by
``geometry.scale``, so a Gaussian's density has the units of voxel values (1/mm). ``mode``:
``"affine"`` (R2-Gaussian's local affine splat, exact in parallel beam) or ``"exact"`` (the
closed-form integral along every pixel's own ray). Each Gaussian reaches the pixels whose ray
passes within 3 sigma of its centre. Forward and backward are gathers: same input, same bits.

The kernels (``cl/projector.cl``), their layout, compiled variants and vector widths, and what a
kernel author may change: docs/kernels.md.
"""
from __future__ import annotations

import os

import numpy as np
import torch

from clgs import runtime
from clgs.errors import ClgsError
from clgs.reference.gaussians import covariance, precision
from clgs.runtime import Operator, real_name, round_up, shared

MODES = ("affine", "exact")
VP = 20
_HIST_BUDGET = 1 << 22  # views x chunks x tiles: the tile counts take 5 ints each (20 bytes)


class ProjectorError(ClgsError, ValueError):
    """Inputs the projector cannot handle, with what to do about them."""


WIDTH_ENV = "CLGS_TILE_WIDTH"
WIDTHS = (8, 16)
# (render, backward) vector widths per (beam, mode) on a device whose native float vector has 16
# lanes, each kept at 16 only where 16 lanes are faster than 8 (docs/kernels.md). The exact cone's
# pixel loops are bound by a division and a square root per pixel, which cost the same per lane
# at either width, so the wider rows' extra masked lanes only add work there.
WIDE = {("cone", "affine"): (16, 16), ("parallel", "affine"): (16, 16),
        ("parallel", "exact"): (16, 8), ("cone", "exact"): (8, 8)}


def _check_width(w, what):
    try:
        ok = int(w) in WIDTHS
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ProjectorError(f"{what} must be 8 or 16 (pixels per vector row), got {w!r}")
    return int(w)


def tile_width(device=None) -> tuple[int, bool]:
    """(width, forced): ``$CLGS_TILE_WIDTH`` (8 or 16) if set, forced on every kernel; else 16
    when the device's native float vector holds 16 lanes (AVX-512 CPUs), applied per kernel as
    ``WIDE`` says, else 8."""
    env = os.environ.get(WIDTH_ENV, "").strip()
    if env:
        return _check_width(env, f"${WIDTH_ENV}"), True
    if device is None:
        device = runtime.device()
    return (16 if int(device.native_vector_width_float) == 16 else 8), False


def view_params(geometry, views, dtype=np.float32) -> np.ndarray:
    """(len(views), 20) per-view parameters in scene units, layout in ``cl/project_setup.h``."""
    vec = geometry.view_vectors(scene=True, views=views)
    nv, nu = geometry.nDetector
    out = np.zeros((len(vec), VP), np.float64)
    for i, row in enumerate(vec):
        first, det, gu, gv = row[0:3], row[3:6], row[6:9], row[9:12]
        gul, gvl = np.linalg.norm(gu), np.linalg.norm(gv)
        eu, ev = gu / gul, gv / gvl
        if geometry.mode == "cone":
            s = first
            rel = det - s
            w = rel - (rel @ eu) * eu - (rel @ ev) * ev
            D = float(np.linalg.norm(w))
            w = w / D
            fx, fy = D / gul, D / gvl
            cx = (nu - 1) / 2.0 - (rel @ eu) / gul
            cy = (nv - 1) / 2.0 - (rel @ ev) / gvl
        else:
            s, w, D = det, first / np.linalg.norm(first), 0.0
            fx, fy, cx, cy = 1.0 / gul, 1.0 / gvl, (nu - 1) / 2.0, (nv - 1) / 2.0
        out[i, :19] = [*s, *eu, *ev, *w, fx, fy, cx, cy, gul, gvl, D]
    return out.astype(dtype)




class GaussianProjector(Operator):
    """Owns the compiled programs (per beam, mode, precision, gradients) and the work buffers.

    Buffers grow when a larger scene comes along and are reused across calls. On a CPU device
    inputs and outputs are NumPy memory wrapped with ``USE_HOST_PTR`` (no copies); on a GPU they
    are copied through pooled device buffers. One projector serialises its own calls.
    """

    SOURCE = "projector.cl"

    # Work-group sizes. PoCL's CPU device runs these kernels fastest one work-item per group
    # (its work-group vectoriser only gets in the way of explicit real8 code); GPUs want groups.
    # Backward: on CPUs each work-item takes PER consecutive Gaussians. (The forward's set-up
    # and binning kernels take a chunk of consecutive Gaussians per work-item and view, one
    # histogram column each; see forward.)
    LOCAL_G_CPU, LOCAL_TILE_CPU, PER_CPU = 1, (1, 1, 1), 16
    LOCAL_G_GPU, LOCAL_TILE_GPU, PER_GPU = 64, (8, 8, 1), 1
    # Forward tile (TW, TH), TW = the render's vector width. Tall tiles on CPUs: a 2-8 pixel
    # Gaussian then mostly falls in one tile row, so there are fewer (tile, Gaussian) pairs to
    # bin, copy and loop over, and fewer tiles walk the chunks' lists (8 x 64 ran binning + fill +
    # render about 20% faster than 8 x 16; at 16 wide, 16 x 64 beat 16 x 32 and 16 x 16, and
    # 256 rows beat 64 by 2-10 % on 10k-50k Gaussians, 128^2 and 256^2 detectors, side by
    # side); GPUs keep the accumulator small.
    TILE_CPU = {8: (8, 256), 16: (16, 256)}
    TILE_GPU = {8: (8, 16), 16: (16, 8)}

    def __init__(self, width: int | None = None, ctx=None, queue=None):
        """``width`` (8 or 16) forces that vector width on every kernel; None: ``tile_width()``.
        ``ctx``/``queue``: where it runs (default: the process's device)."""
        super().__init__(ctx, queue)
        self.LOCAL_G = self.LOCAL_G_CPU if self.cpu else self.LOCAL_G_GPU
        self.LOCAL_TILE = self.LOCAL_TILE_CPU if self.cpu else self.LOCAL_TILE_GPU
        self.PER = self.PER_CPU if self.cpu else self.PER_GPU
        self._token = 0  # counts forward calls; the records in the pool belong to call _rec_token
        self._rec_token: int | None = None
        self.last_token: int | None = None
        self.extra_defines: dict = {}  # tuning experiments only
        if width is None:
            self.width, self.forced = tile_width(self.device)
        else:
            self.width, self.forced = _check_width(width, "width"), True
        self.tile = None  # (TW, TH) to use for every forward instead of the automatic tile (tests, tuning)
        self.backward_width = None  # likewise for the backward's BW
        self._vp_cache: dict = {}
        # Gaussians are set up and binned in chunks, a work-item per (chunk, view), each chunk's
        # tile lists in one region (cl/projector.cl): enough chunks to keep every compute
        # unit busy, and no more on CPUs, where the render reads each tile's entries region by
        # region and longer runs stream better (256 chunks: render about 10% slower than 32).
        cus = int(self.device.max_compute_units)
        self.max_chunks = min(256, max(32, 8 * cus)) if self.cpu else 256
        self._pair_ratio = 2.0  # Gaussian-tile pairs per Gaussian and view in the last forward

    # ----------------------------------------------------------------------------- plumbing
    def widths(self, beam: str, mode: str) -> tuple[int, int]:
        """(render, backward) vector widths for this beam and mode."""
        w = (self.width, self.width) if self.width == 8 or self.forced else WIDE[(beam, mode)]
        tw = self.tile[0] if self.tile is not None else w[0]
        return tw, self.backward_width or w[1]

    def tile_for(self, beam: str, mode: str) -> tuple[int, int]:
        """The forward's tile (TW, TH) for this beam and mode."""
        if self.tile is not None:
            return tuple(self.tile)
        return (self.TILE_CPU if self.cpu else self.TILE_GPU)[self.widths(beam, mode)[0]]

    def program(self, beam: str, mode: str, real: str, grads=(True, True, True)):
        """The compiled program for this variant (looked up once per variant and setting: the
        runtime's own cache costs tens of microseconds a call)."""
        key = (beam, mode, real, tuple(grads), self.tile and tuple(self.tile), self.backward_width,
               tuple(sorted(self.extra_defines.items())))
        return self.variant(key, lambda: self._defines(beam, mode, real, grads))

    def _defines(self, beam, mode, real, grads) -> dict:
        TW, TH = self.tile_for(beam, mode)
        defines = {"REAL": real, "CONE": beam == "cone", "EXACT": mode == "exact", "TW": TW, "TH": TH,
                   "BW": self.widths(beam, mode)[1]}
        defines["NO_GRAD_MEAN"] = not grads[0]
        defines["NO_GRAD_COV"] = not grads[1]
        defines["NO_GRAD_DENSITY"] = not grads[2]
        defines.update(self.extra_defines)
        return defines

    @staticmethod
    def _check(means, mats, densities):
        n = means.shape[0]
        if means.shape != (n, 3) or mats.shape != (n, 6) or densities.shape != (n,):
            raise ProjectorError(
                f"expected means (N,3), matrices (N,6), densities (N,); got {means.shape}, {mats.shape}, "
                f"{densities.shape}")
        if n >= 2**31 // 8:
            raise ProjectorError(f"{n} Gaussians is more than this projector indexes; split the scene")

    def _setup(self, means, mats, densities, geometry, views, mode):
        """Checks, then (real, dtype, number of views, view parameters, geometry.scale)."""
        if mode not in MODES:
            raise ProjectorError(f"mode must be one of {MODES}, got {mode!r}")
        self._check(means, mats, densities)
        real = real_name(means.dtype, "projector inputs", ProjectorError)
        dt = means.dtype
        if mats.dtype != dt or densities.dtype != dt:
            raise ProjectorError(f"means, matrices and densities must share one dtype, got {means.dtype}, "
                                 f"{mats.dtype}, {densities.dtype}")
        # View parameters are kept per geometry (the last few; a Geometry is frozen, its angles
        # read-only), row by row as views are asked for, and per list of views: a training run
        # asks for the same few views again and again (its forward and backward, every epoch),
        # and computing a row costs about 100 us of Python. (The entry holds the geometry, so
        # its id cannot be reused by another object while cached.)
        ent: tuple | None = self._vp_cache.get((id(geometry), dt.str))
        if ent is None or ent[0] is not geometry:
            if len(self._vp_cache) >= 8:
                self._vp_cache.pop(next(iter(self._vp_cache)))
            n = geometry.n_views
            ent = (geometry, np.zeros((n, VP), dt), np.zeros(n, bool), geometry.scale, {})
            self._vp_cache[(id(geometry), dt.str)] = ent
        try:
            vkey = tuple(views)
            vp = ent[4].get(vkey)
        except TypeError:  # not a flat sequence of indices: checked below
            vkey, vp = None, None
        if vp is None:
            idx = np.asarray(views).reshape(-1)
            if idx.size == 0:
                raise ProjectorError("no views asked for: pass at least one view index")
            if idx.dtype.kind not in "iu" or idx.min() < 0 or idx.max() >= geometry.n_views:
                raise ProjectorError(f"view indices must be integers in [0, {geometry.n_views - 1}], got "
                                     f"{idx.tolist()}")
            table, done = ent[1], ent[2]
            new = np.unique(idx[~done[idx]])
            if new.size:
                table[new] = view_params(geometry, new, dt)
                done[new] = True
            vp = table[idx]
            if vkey is not None:
                if len(ent[4]) >= 64:
                    ent[4].pop(next(iter(ent[4])))
                ent[4][vkey] = vp
        return real, dt, len(vp), vp, ent[3]

    # ----------------------------------------------------------------------------- forward
    def forward(self, means: np.ndarray, mats: np.ndarray, densities: np.ndarray, geometry, views,
                mode: str = "affine") -> np.ndarray:
        """Projections (len(views), V, U) from NumPy means (N,3), packed covariance (affine) or
        precision (exact) (N,6) and densities (N,), all float32 or all float64."""
        with self.call():
            real, dt, nv, vp, scale = self._setup(means, mats, densities, geometry, views, mode)
            V, U = geometry.nDetector
            N = means.shape[0]
            out = np.empty((nv, V, U), dt)
            self._token += 1
            self.last_token = self._token
            self._rec_token = None
            if N == 0:
                out[...] = 0
                return out
            beam = geometry.mode
            prog = self.program(beam, mode, real)
            TW, TH = self.tile_for(beam, mode)
            i32 = np.int32
            rec_len = 20 if (mode == "exact" and beam == "cone") else 8
            uses_list = mode == "exact" and beam == "cone"
            b_means = self.io.input(means, "means")
            b_mats = self.io.input(mats, "mats")
            b_rho = self.io.input(densities, "rho")
            b_vp = self.io.input(vp, "vp")
            b_rec = self.io.scratch(f"rec{dt.itemsize}", nv * N * rec_len * dt.itemsize)
            b_box = self.io.scratch("box", nv * N * 16)
            ntx, nty = -(-U // TW), -(-V // TH)
            ntiles = ntx * nty
            nchunks = max(1, min(-(-N // 128), self.max_chunks, _HIST_BUDGET // (nv * ntiles)))
            chunk = round_up(-(-N // nchunks), 8)  # affine set-up: 8 Gaussians per vector
            nchunks = -(-N // chunk)
            b_cnt = self.io.scratch("cnt", nv * nchunks * 4 * ntiles * 4)
            b_cst = self.io.scratch("cst", nv * nchunks * (ntiles + 1) * 4)
            b_rbase = self.io.scratch("rbase", nv * nchunks * 4)
            b_out = self.io.output(out, "out")
            lt = self.LOCAL_TILE
            # The pair count is only known on the device; rather than wait for it between the
            # launches, the lists are sized from the last call's pairs per Gaussian and view (plus
            # a margin, and whatever the pooled buffers already hold), the kernels never write past
            # that capacity, and a call that needed more runs again with larger lists.
            want = int(self._pair_ratio * 1.25 * N * nv) + 4096
            while True:
                # the Gaussian indices of the entries are only read for the exact cone's straddlers
                b_gidx = self.io.scratch("gidx", want * 4 if uses_list else 16)
                b_lst = self.io.scratch(f"lst{dt.itemsize}", want * rec_len * dt.itemsize)
                cap = min(b_lst.size // (rec_len * dt.itemsize), 2**31 - 1)
                if uses_list:
                    cap = min(cap, b_gidx.size // 4)
                b_alloc, alloc = self.io.zeros("alloc", 2)
                self.launch(prog, "preprocess", (nchunks, nv), (1, 1), i32(N), i32(chunk), i32(nchunks),
                            i32(U), i32(V), dt.type(scale), i32(ntx), i32(ntiles), i32(cap), b_means, b_mats,
                            b_rho, b_vp, b_rec, b_box, b_cnt, b_cst, b_rbase, b_alloc, b_lst, b_gidx)
                self.launch(prog, "render", (round_up(ntx, lt[0]), round_up(nty, lt[1]), nv), lt, i32(U),
                            i32(V), i32(ntx), i32(ntiles), i32(nchunks), b_lst, b_cst, b_rbase, b_gidx,
                            b_means, b_mats, b_rho, b_vp, dt.type(scale), b_out)
                self.io.fetch([(b_alloc, alloc), (b_out, out)])  # the call's one wait
                total = int(alloc[0])
                if alloc[1] or total < 0:
                    raise ProjectorError("more Gaussian-tile pairs than 2^31: use fewer views per call")
                if total <= cap:
                    break
                want = total + total // 4
            self._pair_ratio = total / (N * nv)
            self.last_pairs = total
            self._rec_token = self._token
            return out

    # ----------------------------------------------------------------------------- backward
    def backward(self, means, mats, densities, geometry, views, mode, grad_out: np.ndarray,
                 needs=(True, True, True), token=None):
        """Gradients (means (N,3), matrices (N,6), densities (N,)) of sum(grad_out * forward);
        entries not in ``needs`` are returned as None. ``token``: the ``last_token`` of the
        forward call with these very inputs and views; if no other forward ran since, the
        per-(view, Gaussian) set-up it left on the device is reused instead of recomputed."""
        with self.call():
            real, dt, nv, vp, scale = self._setup(means, mats, densities, geometry, views, mode)
            V, U = geometry.nDetector
            N = means.shape[0]
            if grad_out.shape != (nv, V, U):
                raise ProjectorError(f"gradient shape {grad_out.shape} does not match projections {(nv, V, U)}")
            grad_out = np.ascontiguousarray(grad_out, dt)
            shapes = ((N, 3), (N, 6), (N,))
            if N == 0 or not any(needs):
                return tuple(np.zeros(sh, dt) if k else None for sh, k in zip(shapes, needs))
            needs = tuple(bool(k) for k in needs)
            prog = self.program(geometry.mode, mode, real, needs)
            # the kernel writes every entry of the gradients it computes (and none of the others,
            # which get a placeholder buffer)
            outs = [np.empty(sh, dt) if k else None for sh, k in zip(shapes, needs)]
            b = [self.io.output(o, f"grad{k}") if o is not None else self.io.scratch(f"grad{k}", 16)
                 for k, o in enumerate(outs)]
            LG = self.LOCAL_G
            per = self.PER if mode == "exact" else round_up(self.PER, 8)  # affine: 8 Gaussians per vector
            nitems = -(-N // per)
            cached = token is not None and token == self._rec_token
            rec_len = 20 if (mode == "exact" and geometry.mode == "cone") else 8
            b_rec = self.io.scratch(f"rec{dt.itemsize}", nv * N * rec_len * dt.itemsize)
            b_box = self.io.scratch("box", nv * N * 16)
            self.launch(prog, "backward", (round_up(nitems, LG),), (LG,), np.int32(N), np.int32(per),
                        np.int32(nv), np.int32(U), np.int32(V), dt.type(scale),
                        np.int32(cached), b_rec, b_box, self.io.input(means, "means"),
                        self.io.input(mats, "mats"), self.io.input(densities, "rho"), self.io.input(vp, "vp"),
                        self.io.input(grad_out, "gimg"), *b)
            self.io.fetch([(buf, o) for buf, o in zip(b, outs) if o is not None])
            return tuple(outs)


def default_projector() -> GaussianProjector:
    """The process-wide projector (programs and buffers shared by every ``project`` call)."""
    return shared(GaussianProjector)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, mats, densities, geometry, views, mode, projector):
        out = projector.forward(_np(means), _np(mats), _np(densities), geometry, views, mode)
        ctx.save_for_backward(means, mats, densities)
        ctx.args = (geometry, views, mode, projector, projector.last_token)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):
        means, mats, densities = ctx.saved_tensors
        geometry, views, mode, projector, token = ctx.args
        needs = ctx.needs_input_grad[:3]
        g = projector.backward(_np(means), _np(mats), _np(densities), geometry, views, mode,
                               _np(grad.to(means.dtype)), needs, token)
        return tuple(torch.from_numpy(x) if x is not None else None for x in g) + (None, None, None, None)


def _as_views(geometry, views):
    if views is None:
        return list(range(geometry.n_views))
    if isinstance(views, (int, np.integer)):
        return [int(views)]
    return [int(v) for v in views]


def project_packed(means, mats, densities, geometry, views=None, mode: str = "affine",
                   projector: GaussianProjector | None = None) -> torch.Tensor:
    """Like :func:`project` with the packed covariance (affine) or precision (exact) given
    directly, (N, 6) as (xx, xy, xz, yy, yz, zz). Differentiable wrt all three tensors."""
    if mode not in MODES:
        raise ProjectorError(f"mode must be one of {MODES}, got {mode!r}")
    for name, t in (("means", means), ("mats", mats), ("densities", densities)):
        if not isinstance(t, torch.Tensor):
            raise ProjectorError(f"{name} must be a torch tensor, got {type(t).__name__}")
        if t.device.type != "cpu":
            raise ProjectorError(f"{name} is on {t.device}; the projector takes CPU tensors (move with .cpu())")
        if t.dtype != means.dtype:
            raise ProjectorError(f"all inputs must share one dtype: means is {means.dtype}, {name} is {t.dtype}")
    if means.dtype not in (torch.float32, torch.float64):
        raise ProjectorError(f"inputs must be float32 or float64, got {means.dtype}")
    return _Project.apply(means, mats, densities, geometry, _as_views(geometry, views), mode,
                          projector or default_projector())


def project(means, scales, quats, densities, geometry, views=None, mode: str = "affine",
            projector: GaussianProjector | None = None) -> torch.Tensor:
    """Projections (len(views), V, U) of Gaussians, differentiable wrt all four inputs.

    means (N,3) scene coordinates; scales (N,3) activated standard deviations (scene units);
    quats (N,4) raw (w,x,y,z), normalised here; densities (N,) activated. ``views``: view
    indices into ``geometry.angles`` (None: all; an int: one). float32 or float64 by input dtype.
    """
    n = means.shape[0] if means.dim() == 2 else -1
    if means.dim() != 2 or means.shape[1] != 3:
        raise ProjectorError(f"means must be (N, 3), got {tuple(means.shape)}")
    if tuple(scales.shape) != (n, 3) or tuple(quats.shape) != (n, 4) or tuple(densities.shape) != (n,):
        raise ProjectorError(
            f"for N={n} Gaussians expected scales (N,3), quats (N,4), densities (N,); got "
            f"{tuple(scales.shape)}, {tuple(quats.shape)}, {tuple(densities.shape)}")
    for name, t in (("scales", scales), ("quats", quats), ("densities", densities)):
        if t.dtype != means.dtype:
            raise ProjectorError(f"all inputs must share one dtype: means is {means.dtype}, {name} is {t.dtype}")
    if n:
        with torch.no_grad():
            for name, t in (("means", means), ("scales", scales), ("quats", quats), ("densities", densities)):
                if not bool(torch.isfinite(t).all()):
                    raise ProjectorError(f"{name} contains NaN or Inf")
            if not bool((scales > 0).all()):
                raise ProjectorError("scales must be positive (activated standard deviations)")
            if not bool((torch.linalg.vector_norm(quats, dim=-1) > 0).all()):
                raise ProjectorError("a quaternion is zero: rotations need a non-zero quaternion")
    mats = covariance(scales, quats) if mode == "affine" else precision(scales, quats)
    return project_packed(means, mats, densities, geometry, views, mode, projector)
