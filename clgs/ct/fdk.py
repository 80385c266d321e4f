"""FDK (cone beam) and FBP (parallel beam) reconstruction: cosine pre-weighting (cone), redundancy
weights for short arcs, ramp filtering along the detector rows, the view's angular step, and a
voxel-driven backprojection in OpenCL (:mod:`clgs.ops.fdk`). A per-view (vector) scan takes the
same steps on each view's own geometry (:mod:`clgs.ct.fdk_views`). The steps and the weights, and
what is done for a per-view scan: docs/fdk.md."""
from __future__ import annotations

import numpy as np

from clgs.ct import fdk_views
from clgs.ct.filter_names import FILTERS
from clgs.errors import InputError
from clgs.geometry import Geometry
from clgs.io.validate import check_projections
from clgs.ops.fdk import backproject, view_depths


def ramp_filter(length: int, spacing: float, filter: str = "ram-lak"):
    """Frequency response (rfft layout, padded length) of the windowed ramp for rows of ``length``
    samples ``spacing`` mm apart; returns (response, padded_length)."""
    name = str(filter).lower()
    if name not in FILTERS:
        raise InputError(f"unknown filter {filter!r}; choose one of {', '.join(FILTERS)}")
    n_pad = int(2 ** np.ceil(np.log2(max(2 * int(length), 64))))
    k = np.arange(n_pad)
    k = np.where(k < n_pad // 2, k, k - n_pad)  # signed sample offsets, circular
    h = np.zeros(n_pad)
    h[0] = 1.0 / (4.0 * spacing**2)
    odd = (k % 2) != 0
    h[odd] = -1.0 / (np.pi * k[odd] * spacing) ** 2
    resp = np.fft.rfft(h).real * spacing
    f = np.fft.rfftfreq(n_pad)  # cycles per sample, 0 .. 0.5
    if name == "shepp-logan":
        resp *= np.sinc(f)
    elif name == "cosine":
        resp *= np.cos(np.pi * f)
    elif name == "hamming":
        resp *= 0.54 + 0.46 * np.cos(2 * np.pi * f)
    elif name == "hann":
        resp *= 0.5 + 0.5 * np.cos(2 * np.pi * f)
    return resp, n_pad


def _sorted_arc(angles):
    """Angles unwrapped so that the largest circular gap is outside: (order, unwrapped, gaps, full)."""
    b = np.mod(np.asarray(angles, np.float64), 2 * np.pi)
    order = np.argsort(b, kind="stable")
    bs = b[order]
    gaps = np.diff(np.concatenate([bs, bs[:1] + 2 * np.pi]))  # gaps[i]: from i to i+1 (cyclic)
    big = int(np.argmax(gaps))
    med = float(np.median(gaps))
    full = gaps[big] <= 1.5 * med + 1e-9
    start = (big + 1) % b.size
    order = np.roll(order, -start)
    un = np.mod(b[order] - b[order[0]], 2 * np.pi) + b[order[0]]
    if b.size > 1:
        un[1:] = np.maximum.accumulate(un[1:])
    return order, un, np.roll(gaps, -start), full


class Redundancy:
    """The angular steps and redundancy weights of a set of view angles (docs/fdk.md, "The steps"): ``step``
    (n,) and :meth:`weights` of one view's rays, given their fan angles."""

    def __init__(self, angles, short_scan="auto"):
        if short_scan not in ("auto", True, False):
            raise InputError(f"short_scan must be 'auto', True or False, got {short_scan!r}")
        angles = np.asarray(angles, np.float64)
        n = angles.size
        self.constant = None  # a weight for every ray, or None for the taper
        if n == 1:
            self.step, self.constant = np.array([np.pi]), 1.0
            return
        order, un, gaps, full = _sorted_arc(angles)
        if not np.any(gaps[:-1] > 0):  # every view at one angle: each is a copy of a one-view scan
            self.step, self.constant = np.full(n, np.pi / n), 1.0
            return
        step = np.empty(n)
        if full and short_scan is not True:
            step[order] = 0.5 * (gaps + np.roll(gaps, 1))
            self.step, self.constant = step, 0.5
            return
        inner = gaps[:-1]  # gaps between consecutive views along the arc
        st = np.empty(n)
        st[1:-1] = 0.5 * (inner[:-1] + inner[1:])
        st[0], st[-1] = inner[0], inner[-1]
        step[order] = st
        self.step = step
        self.a0 = un[0] - 0.5 * inner[0]
        self.a1 = un[-1] + 0.5 * inner[-1]
        arc = self.a1 - self.a0
        if short_scan is False:
            self.constant = min(1.0, np.pi / arc)
            return
        self.eps = max(float(np.clip(arc - np.pi, 2 * np.median(inner), 0.5 * arc)), 1e-9)
        # (many repeated angles make the median gap 0: the floor keeps the taper finite)
        self.beta = np.empty(n)
        self.beta[order] = un

    def _taper(self, beta):
        d = np.minimum(beta - self.a0, self.a1 - beta)
        h = np.sin(0.5 * np.pi * np.clip(d / self.eps, 0.0, 1.0)) ** 2
        return np.where(d >= 0, np.maximum(h, 1e-6), 0.0)

    def weights(self, view: int, gamma) -> np.ndarray:
        """Weights of view ``view``'s rays of fan angles ``gamma`` (any shape)."""
        gamma = np.asarray(gamma, np.float64)
        if self.constant is not None:
            return np.full(gamma.shape, self.constant)
        beta = self.beta[view]
        conj = beta + np.pi - 2 * gamma
        conj = self.a0 + np.mod(conj - self.a0, 2 * np.pi)
        h = self._taper(np.array([beta]))
        return h / (h + self._taper(conj))


def view_weights(geometry: Geometry, short_scan="auto"):
    """(n_views,) angular steps and the redundancy weights, in the geometry's view order: (n_views, U)
    for a circular scan, (n_views, V, U) per pixel for a per-view one (the fan angles of a turned
    detector change along its columns).

    The rules: docs/fdk.md, "The steps".
    """
    if not geometry.is_circular:
        orb = fdk_views.orbit(geometry)
        red = Redundancy(orb.angles, short_scan)
        _, dists, _ = view_depths(geometry)
        w = [red.weights(i, fdk_views.fan_and_cosine(geometry, orb, i, dists[i])[0]) for i in range(geometry.n_views)]
        return red.step, np.stack(w)
    nu = geometry.nDetector[1]
    if geometry.mode == "cone":
        u_mm = (np.arange(nu) - 0.5 * (nu - 1)) * geometry.dDetector[1] + geometry.offDetector[1]
        gamma = np.arctan(u_mm / geometry.DSD)
    else:
        gamma = np.zeros(nu)
    red = Redundancy(geometry.angles, short_scan)
    return red.step, np.stack([red.weights(i, gamma) for i in range(geometry.n_views)])


#: a row is truncated when its edge pixels hold more than this fraction of the projections' maximum
TRUNCATION_LEVEL = 0.05


def is_truncated(projections, level: float = TRUNCATION_LEVEL) -> bool:
    """Whether the object reaches past the detector's sides (u): an edge column of some view
    holds more than ``level`` of the largest line integral."""
    p = np.asarray(projections)
    top = float(np.max(p)) if p.size else 0.0
    edges = max(float(np.max(p[..., 0])), float(np.max(p[..., -1]))) if p.size else 0.0
    return top > 0 and edges > level * top


def extrapolate_rows(p, width: int) -> np.ndarray:
    """Rows (..., U) extended by ``width`` columns on each side, each edge value rolled off to zero
    by a half cosine: a truncated object's rows end smoothly, so the ramp filter makes no bright
    rim at the detector's edge (the classic truncation artefact inside the field of view)."""
    w = int(width)
    k = np.arange(1, w + 1, dtype=np.float64)
    roll = 0.5 * (1.0 + np.cos(np.pi * k / (w + 1)))  # 1 -> 0 away from the edge
    left = p[..., :1] * roll[::-1]
    right = p[..., -1:] * roll
    return np.concatenate([left, p, right], axis=-1)


def filter_projections(projections, geometry: Geometry, filter="ram-lak", short_scan="auto",
                       truncation="auto") -> np.ndarray:
    """Steps 1-4 of docs/fdk.md, "The steps": weighted, ramp-filtered projections (n, V, U), float64.

    ``truncation``: ``"auto"`` extends truncated rows (:func:`is_truncated`) past the detector's
    sides before filtering (:func:`extrapolate_rows`, half a row on each side), ``True`` always,
    ``False`` never (zero padding)."""
    g = geometry
    if truncation not in ("auto", True, False):
        raise InputError(f"truncation must be 'auto', True or False, got {truncation!r}")
    p = np.asarray(projections, np.float64)
    nv, nu = g.nDetector
    if g.is_circular:
        dv, du = g.dDetector
        u_mm = (np.arange(nu) - 0.5 * (nu - 1)) * du + g.offDetector[1]
        v_mm = (np.arange(nv) - 0.5 * (nv - 1)) * dv + g.offDetector[0]
        step, red = view_weights(g, short_scan)
        if g.mode == "cone":
            cosw = g.DSD / np.sqrt(g.DSD**2 + u_mm[None, :] ** 2 + v_mm[:, None] ** 2)
            p = p * cosw[None]
            spacing = du * g.DSO / g.DSD
        else:
            spacing = du
        p = p * red[:, None, :]
        scale = step
    else:
        p, scale = _weigh_views(p, g, short_scan)
        spacing = 1.0  # each view's own pixel pitch is in ``scale``
    ext = 0
    if truncation is True or (truncation == "auto" and is_truncated(projections)):
        ext = max(8, nu // 2)
        p = extrapolate_rows(p, ext)
    resp, n_pad = ramp_filter(nu + 2 * ext, spacing, filter)
    spec = np.fft.rfft(p, n=n_pad, axis=-1)
    spec *= resp
    q = np.fft.irfft(spec, n=n_pad, axis=-1)[..., ext:ext + nu]
    return q * scale[:, None, None]


def _weigh_views(p: np.ndarray, g: Geometry, short_scan):
    """Steps 1-2 for a per-view scan, view by view, on its own orbit (:mod:`clgs.ct.fdk_views`);
    returns (weighted projections, per-view factor of step 4 to apply after a unit-spacing ramp).

    The factor ``db R D / (ref^2 du)`` is the circular ``db`` with the ramp's spacing ``du DSO/DSD``
    and the kernel's ``(DSO / depth)^2`` written for the view's own source distance from the axis
    ``R``, source-detector distance ``D``, reference depth ``ref`` (see
    :func:`clgs.ops.fdk.view_depths`) and u pixel pitch ``du``."""
    orb = fdk_views.orbit(g)
    red = Redundancy(orb.angles, short_scan)
    _, dists, refs = view_depths(g)
    du = np.linalg.norm(g.frame_vectors()[:, 6:9], axis=1)
    out = np.empty_like(p)
    for i in range(g.n_views):
        gamma, cosine = fdk_views.fan_and_cosine(g, orb, i, dists[i])
        out[i] = p[i] * (cosine * red.weights(i, gamma))
    scale = red.step / du
    if g.mode == "cone":
        scale = scale * orb.radius * dists / refs**2
    return out, scale


def fdk(projections, geometry: Geometry, filter: str = "ram-lak", short_scan="auto", dtype=np.float32,
        truncation="auto") -> np.ndarray:
    """FDK reconstruction (FBP when ``geometry.mode == "parallel"``): (Z, Y, X) volume, values per mm.

    ``projections`` are (n_views, V, U) line integrals. ``filter`` is one of
    ``ram-lak``, ``shepp-logan``, ``cosine``, ``hamming``, ``hann``; ``short_scan`` is ``"auto"``
    (redundancy weights when the angles do not cover a full circle), ``True`` or ``False``.
    ``dtype=np.float64`` backprojects in double precision. ``truncation``: see
    :func:`filter_projections` (``"auto"``: rows of an object wider than the detector are extended
    smoothly before filtering; untruncated scans are filtered as with ``False``).
    """
    from clgs.progress import phase

    p = check_projections(projections, geometry, neg_tolerance=None, source="fdk")
    name = str(filter).lower()
    if name not in FILTERS:
        raise InputError(f"unknown filter {filter!r}; choose one of {', '.join(FILTERS)}")
    # a phase line: the first call also builds the backprojector's OpenCL program (seconds)
    with phase(f"FDK of {p.shape[0]} views on a {'x'.join(map(str, geometry.nVoxel))} grid"):
        q = filter_projections(p, geometry, name, short_scan, truncation)
        vol = backproject(q.astype(np.float64 if dtype == np.float64 else np.float32), geometry)
    return vol.astype(dtype, copy=False)
