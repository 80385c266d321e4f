"""FDK (cone beam) and FBP (parallel beam) reconstruction.

Steps, for view ``i`` at angle ``b_i``:

1. cone beam only: cosine pre-weighting ``DSD / sqrt(DSD^2 + U^2 + V^2)`` with ``(U, V)`` the
   pixel's position on the detector in mm (offsets included);
2. redundancy weights ``w_i(u)`` (below);
3. ramp filtering along u: the band-limited ramp built in the spatial domain (no DC bias),
   zero-padded to at least twice the row length, applied by FFT, times the chosen window
   (``ram-lak``, ``shepp-logan``, ``cosine``, ``hamming``, ``hann``); the sample spacing is the
   pixel size scaled to the rotation axis (``dU DSO / DSD`` for cone);
4. times the view's angular step ``db_i`` (half the distance to its neighbours, so non-uniform
   angles are integrated correctly);
5. voxel-driven backprojection in OpenCL with bilinear interpolation and, for cone beam, the
   distance weight ``(DSO / depth)^2``.

Redundancy weights. A full circle (no gap in the angles larger than 1.5 median steps) measures
every line twice: ``w = 1/2``. Otherwise the arc is short and the weights are *normalised
redundancy weights*, a generalisation of Parker's: every view gets a smooth taper
``h = sin^2`` near the two ends of the arc, and the weight of a measured line is
``h(b) / (h(b) + h(b_c))`` where ``b_c = b + pi - 2 gamma`` is the angle at which the same line
is measured from the other side (``gamma = atan(U / DSD)`` the fan angle of column U, 0 for
parallel beam), with ``h(b_c) = 0`` when ``b_c`` lies outside the arc. So the weights of the two
measurements of a line always sum to one, and a line measured once gets weight one. For an arc of
``pi + fan`` or more this is a valid short-scan weighting like Parker's (taper width
``arc - pi``). For shorter arcs (the 0-180 degree arcs of sparse-view studies are shorter than
``pi + fan``) some lines are measured once near the arc ends and a few not at all: they get
weight one or are missing, which gives the usual limited-angle artefacts but no bias in the
density of the lines that were measured. ``short_scan=False`` turns the weighting off and scales
every view by ``pi / arc`` instead (right mean density, more artefacts); ``True`` forces it even
for a full circle. A single view is backprojected with ``db = pi`` and weight one.
"""
from __future__ import annotations

import numpy as np

from clgs.io.validate import check_projections
from clgs.geometry import Geometry
from clgs.ops.fdk import backproject
from clgs.errors import InputError

FILTERS = ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")


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


def require_circular(geometry: Geometry) -> None:
    """FDK's weights hold for a circular orbit only: a per-view (vector) geometry is refused."""
    if not geometry.is_circular:
        raise InputError("FDK/FBP needs a circular scan (TIGRE's DSO, DSD, angles); this geometry is given per "
                         "view as vectors. Reconstruct it with SART (--method sart) or a Gaussian method "
                         "(--method r2gs, or shape for an anatomy), which take any per-view geometry.")


def view_weights(geometry: Geometry, short_scan="auto"):
    """(n_views,) angular steps and (n_views, U) redundancy weights, in the geometry's view order.

    See the module docstring for the rules.
    """
    angles = geometry.angles
    n = angles.size
    nu = geometry.nDetector[1]
    if geometry.mode == "cone":
        u_mm = (np.arange(nu) - 0.5 * (nu - 1)) * geometry.dDetector[1] + geometry.offDetector[1]
        gamma = np.arctan(u_mm / geometry.DSD)
    else:
        gamma = np.zeros(nu)
    if short_scan not in ("auto", True, False):
        raise InputError(f"short_scan must be 'auto', True or False, got {short_scan!r}")
    if n == 1:
        return np.array([np.pi]), np.ones((1, nu))
    order, un, gaps, full = _sorted_arc(angles)
    if not np.any(gaps[:-1] > 0):  # every view at one angle: each is a copy of a one-view scan
        return np.full(n, np.pi / n), np.ones((n, nu))
    step = np.empty(n)
    if full and short_scan is not True:
        step[order] = 0.5 * (gaps + np.roll(gaps, 1))
        return step, np.full((n, nu), 0.5)
    inner = gaps[:-1]  # gaps between consecutive views along the arc
    s = np.empty(n)
    s[1:-1] = 0.5 * (inner[:-1] + inner[1:])
    s[0], s[-1] = inner[0], inner[-1]
    step[order] = s
    a0 = un[0] - 0.5 * inner[0]
    a1 = un[-1] + 0.5 * inner[-1]
    arc = a1 - a0
    if short_scan is False:
        return step, np.full((n, nu), min(1.0, np.pi / arc))
    eps = float(np.clip(arc - np.pi, 2 * np.median(inner), 0.5 * arc))
    eps = max(eps, 1e-9)  # many repeated angles make the median gap 0: keep the taper finite

    def taper(beta):
        d = np.minimum(beta - a0, a1 - beta)
        inside = d >= 0
        h = np.sin(0.5 * np.pi * np.clip(d / eps, 0.0, 1.0)) ** 2
        return np.where(inside, np.maximum(h, 1e-6), 0.0)

    w = np.empty((n, nu))
    for idx, beta in zip(order, un):
        conj = beta + np.pi - 2 * gamma
        conj = a0 + np.mod(conj - a0, 2 * np.pi)
        h = taper(np.array([beta]))
        hc = taper(conj)
        w[idx] = h / (h + hc)
    return step, w


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
    """Steps 1-4 of the module docstring: weighted, ramp-filtered projections (n, V, U), float64.

    ``truncation``: ``"auto"`` extends truncated rows (:func:`is_truncated`) past the detector's
    sides before filtering (:func:`extrapolate_rows`, half a row on each side), ``True`` always,
    ``False`` never (zero padding)."""
    g = geometry
    require_circular(g)
    p = np.asarray(projections, np.float64)
    nv, nu = g.nDetector
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
    if truncation not in ("auto", True, False):
        raise InputError(f"truncation must be 'auto', True or False, got {truncation!r}")
    ext = 0
    if truncation is True or (truncation == "auto" and is_truncated(projections)):
        ext = max(8, nu // 2)
        p = extrapolate_rows(p, ext)
    resp, n_pad = ramp_filter(nu + 2 * ext, spacing, filter)
    spec = np.fft.rfft(p, n=n_pad, axis=-1)
    spec *= resp
    q = np.fft.irfft(spec, n=n_pad, axis=-1)[..., ext:ext + nu]
    return q * step[:, None, None]


def fdk(projections, geometry: Geometry, filter: str = "ram-lak", short_scan="auto", dtype=np.float32,
        truncation="auto") -> np.ndarray:
    """FDK reconstruction (FBP when ``geometry.mode == "parallel"``): (Z, Y, X) volume, values per mm.

    ``projections`` are (n_views, V, U) line integrals. ``filter`` is one of
    ``ram-lak``, ``shepp-logan``, ``cosine``, ``hamming``, ``hann``; ``short_scan`` is ``"auto"``
    (redundancy weights when the angles do not cover a full circle), ``True`` or ``False``.
    ``dtype=np.float64`` backprojects in double precision. ``truncation``: see
    :func:`filter_projections` (``"auto"``: rows of an object wider than the detector are extended
    smoothly before filtering; untruncated scans are filtered exactly as before).
    """
    require_circular(geometry)
    p = check_projections(projections, geometry, neg_tolerance=None, source="fdk")
    name = str(filter).lower()
    if name not in FILTERS:
        raise InputError(f"unknown filter {filter!r}; choose one of {', '.join(FILTERS)}")
    q = filter_projections(p, geometry, name, short_scan, truncation)
    return backproject(q.astype(np.float64 if dtype == np.float64 else np.float32), geometry).astype(dtype, copy=False)
