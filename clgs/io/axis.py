"""Where the rotation axis meets the detector, found three independent ways, and the detector's
roll (in-plane tilt) from a 180-degree pair.

One estimator can be wrong without saying so (a background pulls the centre of mass; a truncated
object biases it; a pair of views may not exist). So :func:`find_axis` runs all that apply, each
with its own figure of merit, and says how far they agree:

* ``pair``: the view at ``theta + 180`` degrees, mirrored, is the view at ``theta`` mirrored about
  the axis. Least squares over the axis column (a coarse search, then a bounded refinement with
  cubic-spline resampling) and, with four rows or more, the detector's roll, fitted on the whole
  image (the mirrored view is the first turned by twice the roll about the axis). When no view
  lies exactly 180 degrees from another (a 180-degree arc that stops one step short), the
  opposite view is interpolated in angle (linearly, from its neighbour), to first order. Several
  pairs (a 360-degree scan) are averaged. Figure: the mismatch (relative RMS difference of the
  matched pair).
* ``sinogram``: a filtered backprojection of a few rows near the middle, tried over axis columns
  (coarse on columns binned to about 128, then at full resolution), keeping the column where the
  slice's negative mass (the sum of its negative values) is least: a consistent sinogram of a
  non-negative object reconstructs without negative lobes, a wrong axis adds them. Figure: the
  contrast (how much larger the metric is 3 pixels either side).
* ``com``: the attenuation-weighted mean column of each view follows
  ``c0 + a cos(theta) + b sin(theta)``; fitted after each view's air background is removed (a
  background pulls the mean towards the detector's middle). Biased when the object crosses the
  detector's edge: then reported but not counted. Figure: the fit's RMS residual.

Which is chosen: when the counted estimates agree within :data:`AGREE_PX`, the first available of
``pair``, ``sinogram``, ``com`` (the pair compares two measured views directly, with no model of the
scan; the sinogram search uses every view but depends on the reconstruction's artefacts; the
centre of mass assumes a complete, background-free object). When they disagree, two that agree
outvote the third (the first of those two is chosen); otherwise the first available. A
disagreement is always reported with every figure (``warning``).

Search range: the axis is looked for within the detector's middle half (columns N/4 to 3N/4),
where half of every view overlaps its mirror; give the column by hand otherwise. Cone beam: the
estimators use the central rows, where a cone-beam scan is close to a fan of parallel rays; they
are approximate (opposite views differ by magnification) and the roll is not estimated.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage, optimize

from clgs.errors import ClgsError

__all__ = ["AxisError", "find_axis", "pair_axis", "sinogram_axis", "com_axis", "opposite_pairs", "AGREE_PX",
           "ESTIMATORS"]

AGREE_PX = 1.0
ESTIMATORS = ("pair", "sinogram", "com")
NAMES = {"pair": "180-degree pair", "sinogram": "FBP sharpness", "com": "centre of mass"}


class AxisError(ClgsError, ValueError):
    """The axis cannot be found from these projections."""


# ----------------------------------------------------------------------------- pairs of views
def _wrap(deg):
    return (np.asarray(deg, np.float64) + 180.0) % 360.0 - 180.0


def opposite_pairs(angles_rad, limit: int = 8) -> list:
    """[(i, j, gap_deg)]: up to ``limit`` views ``i`` with a view ``j`` at ``theta_i + 180 + gap``
    degrees, ``|gap|`` the smallest the scan offers and at most 2 degrees and 1.5 angular steps;
    empty when there is none."""
    th = np.rad2deg(np.asarray(angles_rad, np.float64).reshape(-1))
    n = th.size
    if n < 2:
        return []
    tol = min(2.0, 1.5 * max(_step(th), 1e-6))
    found = []
    for i in range(n):
        off = _wrap(th - (th[i] + 180.0))
        off[i] = np.inf
        j = int(np.argmin(np.abs(off)))
        if abs(off[j]) <= tol and (i < j or abs(_wrap(th[i] - th[j] - 180.0)) > abs(off[j]) + 1e-9):
            found.append((i, j, float(off[j])))
    if not found:
        return []
    best = min(abs(f[2]) for f in found)
    found = [f for f in found if abs(f[2]) <= best + 1e-6]
    if len(found) > limit:
        found = [found[int(t)] for t in np.linspace(0, len(found) - 1, limit).round()]
    return found


def _step(th_deg) -> float:
    return float(np.median(np.abs(np.diff(np.sort(np.asarray(th_deg) % 360.0))))) if len(th_deg) > 2 else 180.0


def _view_at(p, th_deg, index: int, offset_deg: float) -> np.ndarray:
    """View ``index`` turned by ``offset_deg`` (small): linear in angle between it and the view on
    the far side of the target (or, at the end of the arc, the neighbour on its own side)."""
    if abs(offset_deg) < 1e-9:
        return p[index]
    off = _wrap(th_deg - (th_deg[index] + offset_deg))
    off[index] = np.inf
    reach = 1.5 * max(_step(th_deg), 1e-6) + abs(offset_deg)
    far = np.where((np.sign(off) == np.sign(offset_deg)) & (np.abs(off) <= reach))[0]
    near = np.where((np.sign(off) == -np.sign(offset_deg)) & (np.abs(off) <= reach))[0]
    pick = far if far.size else near
    if not pick.size:
        return p[index]
    k = int(pick[np.argmin(np.abs(off[pick]))])
    dk = float(_wrap(th_deg[k] - th_deg[index]))
    w = offset_deg / dk
    return (1.0 - w) * p[index] + w * p[k]


def _pair_cost(A, coeffs, c, gamma, rows, n_rows):
    """Normalised squared difference between view ``A`` (rows ``rows`` of the detector) and the
    opposite view (spline ``coeffs``) mirrored about the axis at column ``c`` (middle row) with
    roll ``gamma`` (radians)."""
    nV_sel, nU = A.shape
    cv = (n_rows - 1) / 2.0
    iu = np.arange(nU, dtype=np.float64)[None, :]
    iv = np.asarray(rows, np.float64)[:, None]
    cg, sg = np.cos(gamma), np.sin(gamma)
    du, dv = iu - c, iv - cv
    u = du * cg - dv * sg
    z = du * sg + dv * cg
    iu2 = c - u * cg + z * sg
    iv2 = cv + u * sg + z * cg
    iu2, iv2 = np.broadcast_to(iu2, A.shape), np.broadcast_to(iv2, A.shape)
    valid = (iu2 >= 0) & (iu2 <= nU - 1) & (iv2 >= 0) & (iv2 <= n_rows - 1)
    if valid.sum() < 0.25 * A.size:
        return 1.0
    B = ndimage.map_coordinates(coeffs, [iv2[valid], iu2[valid]], order=3, mode="nearest", prefilter=False)
    a = A[valid]
    den = float(np.sum(a * a + B * B))
    return float(np.sum((a - B) ** 2) / den) if den > 0 else 1.0


def _fit_pair(A_full, B_full, fit_roll: bool, max_rows: int = 48):
    """(column at the middle row, roll radians, cost) for one pair of views (rows, columns)."""
    n_rows, nU = A_full.shape
    rows = np.unique(np.linspace(0, n_rows - 1, min(n_rows, max_rows)).round().astype(int))
    A = A_full[rows].astype(np.float64)
    coeffs = ndimage.spline_filter(B_full.astype(np.float64), order=3, mode="nearest")
    lo, hi = (nU - 1) / 4.0, 3 * (nU - 1) / 4.0
    coarse = np.arange(np.ceil(lo * 2) / 2, hi + 1e-9, 0.5)
    sub = rows if len(rows) <= 16 else rows[np.linspace(0, len(rows) - 1, 16).round().astype(int)]
    A_sub = A_full[sub].astype(np.float64)
    costs = [_pair_cost(A_sub, coeffs, c, 0.0, sub, n_rows) for c in coarse]
    c0 = float(coarse[int(np.argmin(costs))])
    res = optimize.minimize_scalar(lambda c: _pair_cost(A, coeffs, c, 0.0, rows, n_rows),
                                   bounds=(c0 - 1.0, c0 + 1.0), method="bounded", options={"xatol": 1e-4})
    c1, gamma = float(res.x), 0.0
    if not fit_roll:
        return c1, 0.0, float(res.fun)
    # per-row axis columns (each row alone) give the roll's first estimate: the axis column grows
    # by tan(roll) per row
    per_row, weight = [], []
    for r in rows:
        one = A_full[r:r + 1].astype(np.float64)
        if not np.any(one):
            continue
        rr = optimize.minimize_scalar(lambda c, one=one, r=r: _row_cost(one[0], B_full[r], c),
                                      bounds=(c1 - 3.0, c1 + 3.0), method="bounded", options={"xatol": 1e-4})
        per_row.append((r, float(rr.x)))
        weight.append(float(np.sum(one ** 2)))
    if len(per_row) >= 2:
        r_, c_ = np.array(per_row).T
        wts = np.asarray(weight)
        keep = wts >= 0.1 * wts.max()
        if keep.sum() >= 2:
            slope = np.polyfit(r_[keep] - (n_rows - 1) / 2.0, c_[keep], 1, w=np.sqrt(wts[keep]))[0]
            gamma = float(np.arctan(slope))
    res2 = optimize.minimize(lambda x: _pair_cost(A, coeffs, x[0], x[1], rows, n_rows), [c1, gamma],
                             method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-12,
                                                            "initial_simplex": [[c1, gamma], [c1 + 0.3, gamma],
                                                                                [c1, gamma + 0.005]]})
    return float(res2.x[0]), float(res2.x[1]), float(res2.fun)


def _row_cost(a, b, c):
    """One row: normalised squared difference of ``a`` and ``b`` mirrored about column ``c``."""
    nU = a.size
    iu = np.arange(nU, dtype=np.float64)
    src = 2 * c - iu
    valid = (src >= 0) & (src <= nU - 1)
    if valid.sum() < 0.25 * nU:
        return 1.0
    bb = ndimage.map_coordinates(np.asarray(b, np.float64), [src[valid]], order=3, mode="nearest")
    aa = np.asarray(a, np.float64)[valid]
    den = float(np.sum(aa * aa + bb * bb))
    return float(np.sum((aa - bb) ** 2) / den) if den > 0 else 1.0


def pair_axis(proj, angles_rad, fit_roll: bool = True, smooth: float = 1.0) -> dict:
    """The ``pair`` estimator (module doc): {"column", "tilt_deg" (None with fewer than 4 rows),
    "mismatch_percent", "pairs", "gap_deg"}, or {"available": False, "why"}. Both views are
    smoothed along the rows (Gaussian, ``smooth`` pixels) first: the same blur on both moves
    nothing and keeps the resampling's error below the figures sought."""
    p = np.asarray(proj, np.float64)
    th = np.rad2deg(np.asarray(angles_rad, np.float64).reshape(-1))
    pairs = opposite_pairs(angles_rad)
    if not pairs:
        return {"available": False, "why": "no two views lie 180 degrees apart (within 2 degrees)"}
    fit_roll = fit_roll and p.shape[1] >= 4  # two or three rows leave the slope to noise
    cols, rolls, costs = [], [], []
    for i, j, gap in pairs:
        # an inexact pair meets half-way: each view turned by half the gap, towards the other
        a = _view_at(p, th, i, gap / 2.0)
        b = _view_at(p, th, j, -gap / 2.0)
        if smooth:
            a = ndimage.gaussian_filter1d(a, smooth, axis=-1, mode="nearest")
            b = ndimage.gaussian_filter1d(b, smooth, axis=-1, mode="nearest")
        c, g, cost = _fit_pair(a, b, fit_roll)
        cols.append(c)
        rolls.append(g)
        costs.append(cost)
    i, j, gap = pairs[0]
    out = {"available": True, "column": float(np.mean(cols)),
           "mismatch_percent": float(100 * np.sqrt(2 * np.mean(costs))),
           "pairs": [[int(a), int(b)] for a, b, _ in pairs], "gap_deg": float(gap),
           "tilt_deg": float(np.rad2deg(np.mean(rolls))) if fit_roll else None}
    if abs(gap) > 1e-6:
        out["interpolated"] = (f"views {i} and {j} lie {180 + gap:.4g} degrees apart: each turned by half the "
                               f"{abs(gap):.3g}-degree gap (linear in angle with its neighbour)")
    if len(cols) > 1:
        out["spread_between_pairs_pixels"] = float(np.ptp(cols))
    return out


# ----------------------------------------------------------------------------- FBP sharpness
def _ramp(n: int) -> np.ndarray:
    """Frequency response of the discrete ramp (Ram-Lak) filter for a padded length ``n``."""
    k = np.concatenate([np.arange(1, n // 2 + 1, 2), np.arange(n // 2 - 1, 0, -2)])
    h = np.zeros(n)
    h[0] = 0.25
    h[1::2] = -1.0 / (np.pi * k) ** 2
    return 2 * np.real(np.fft.fft(h))


def _filtered(sino: np.ndarray, upsample: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(ramp-filtered sinogram sampled ``upsample`` times per column (cubic spline), the column
    of each sample): rows padded by their edge values to reduce truncation artefacts. The fine
    sampling keeps the backprojection's linear interpolation from favouring whole columns."""
    n_views, n = sino.shape
    size = int(2 ** np.ceil(np.log2(2 * n)))
    left = (size - n) // 2
    padded = np.pad(sino, ((0, 0), (left, size - n - left)), mode="edge")
    q = np.real(np.fft.ifft(np.fft.fft(padded, axis=1) * _ramp(size)[None], axis=1))
    fine = np.arange(0, size - 1 + 1e-9, 1.0 / upsample)
    rows = np.repeat(np.arange(n_views, dtype=np.float64)[:, None], fine.size, 1)
    q_fine = ndimage.map_coordinates(q, [rows, np.broadcast_to(fine, rows.shape)], order=3, mode="nearest")
    return q_fine, fine - left


def _negative_mass(q, grid, angles, c, pts) -> float:
    """Sum of the negative values of the filtered backprojection (points ``pts`` relative to the
    axis, in pixels) with the axis at column ``c``."""
    x, y = pts
    img = np.zeros(x.shape)
    for qq, t in zip(q, angles):
        img += np.interp(c - x * np.sin(t) + y * np.cos(t), grid, qq)
    return float(-img[img < 0].sum() / len(angles))


def _disk(radius: float, max_points: int = 20000):
    stride = max(1.0, np.sqrt(np.pi * radius ** 2 / max_points))
    r = np.arange(-radius, radius + 1e-9, stride)
    x, y = np.meshgrid(r, r)
    inside = x ** 2 + y ** 2 <= radius ** 2
    return x[inside], y[inside]


def _search(metric, candidates):
    values = np.array([metric(c) for c in candidates])
    return candidates[int(np.argmin(values))], values


def sinogram_axis(proj, angles_rad, rows=None) -> dict:
    """The ``sinogram`` estimator (module doc): {"column", "rows", "contrast_percent"}, or
    {"available": False, "why"}."""
    p = np.asarray(proj, np.float64)
    theta = np.asarray(angles_rad, np.float64).reshape(-1)
    th = np.rad2deg(theta)
    half = _wrap(th - th[0]) % 360.0 < 180.0 - 1e-6  # a 360-degree scan: its first half (a wrong
    p, theta = p[half], theta[half]  # axis blurs a full turn symmetrically, without negative lobes)
    n_views, n_rows, nU = p.shape
    if n_views < 8:
        return {"available": False, "why": f"{n_views} views are too few for a reconstruction"}
    if rows is None:
        energy = np.sum(p ** 2, axis=(0, 2))
        middle = (n_rows - 1) / 2.0
        order = np.argsort(np.abs(np.arange(n_rows) - middle), kind="stable")
        rows = [int(r) for r in order if energy[r] >= 0.2 * energy.max()][:3]
    if not rows:
        return {"available": False, "why": "no row holds any attenuation"}
    sinos = [p[:, r, :] for r in rows]
    # coarse: columns binned to about 128
    b = max(1, nU // 128)
    nb = nU // b
    coarse_q = [_filtered(s[:, :nb * b].reshape(n_views, nb, b).mean(2)) for s in sinos]
    pts = _disk((nb - 1) / 4.0 - 1.0, max_points=3000)
    cand = np.arange(np.ceil((nb - 1) / 4.0), 3 * (nb - 1) / 4.0 + 1e-9, 1.0)
    cb, _ = _search(lambda c: sum(_negative_mass(q, lf, theta, c, pts) for q, lf in coarse_q), cand)
    guess = cb * b + (b - 1) / 2.0
    full_q = [_filtered(s) for s in sinos]
    pts = _disk((nU - 1) / 4.0 - 1.0)
    lo, hi = (nU - 1) / 4.0, 3 * (nU - 1) / 4.0
    cand = np.arange(max(lo, guess - 1.5 * b - 2), min(hi, guess + 1.5 * b + 2) + 1e-9, 0.5)

    def metric(c):
        return sum(_negative_mass(q, lf, theta, c, pts) for q, lf in full_q)

    best, _ = _search(metric, cand)
    res = optimize.minimize_scalar(metric, bounds=(max(lo, best - 0.5), min(hi, best + 0.5)), method="bounded",
                                   options={"xatol": 0.01})
    column = float(res.x)
    m0 = metric(column)
    side = [metric(column + d) for d in (-3.0, 3.0) if lo <= column + d <= hi]
    contrast = float(100 * (np.mean(side) - m0) / m0) if side and m0 > 0 else None
    return {"available": True, "column": column, "rows": [int(r) for r in rows], "contrast_percent": contrast}


# ----------------------------------------------------------------------------- centre of mass
def com_axis(proj, angles_rad, background=None) -> dict:
    """The ``com`` estimator (module doc): {"column", "rms_residual_pixels", "background_removed",
    "truncated_views", "counted"}, or {"available": False, "why"}. ``background`` (n_views,): each
    view's air level; found here (:func:`clgs.io.air.air_background`) when None."""
    from clgs.io.air import air_background

    p = np.asarray(proj, np.float64)
    theta = np.asarray(angles_rad, np.float64).reshape(-1)
    span = float(np.ptp(np.unwrap(theta))) if theta.size > 1 else 0.0
    if theta.size < 3 or span < np.pi / 2:
        return {"available": False, "why": "needs at least 3 views over at least 90 degrees"}
    note = None
    if background is None:
        try:
            background, _ = air_background(p)
        except ValueError as exc:
            background, note = np.zeros(len(p)), f"no air background removed ({exc})"
    profile = np.clip(p.mean(axis=1) - np.asarray(background)[:, None], 0.0, None)
    mass = profile.sum(axis=1)
    if np.any(mass <= 0):
        return {"available": False, "why": "a view holds no attenuation"}
    cols = np.arange(p.shape[2], dtype=np.float64)
    com = (profile * cols).sum(axis=1) / mass
    A = np.stack([np.ones_like(theta), np.cos(theta), np.sin(theta)], axis=1)
    coef, *_ = np.linalg.lstsq(A, com, rcond=None)
    resid = com - A @ coef
    peak = profile.max(axis=1)
    truncated = int(np.count_nonzero((profile[:, 0] > 0.05 * peak) | (profile[:, -1] > 0.05 * peak)))
    out = {"available": True, "column": float(coef[0]), "rms_residual_pixels": float(np.sqrt(np.mean(resid ** 2))),
           "background_removed_min": float(np.min(background)), "background_removed_max": float(np.max(background)),
           "truncated_views": truncated, "counted": truncated == 0}
    if truncated:
        out["why_not_counted"] = (f"the object crosses the detector's edge in {truncated} of {len(p)} views "
                                  "(the centre of mass is biased)")
    if note:
        out["note"] = note
    return out


# ----------------------------------------------------------------------------- all together
def find_axis(proj, angles_rad, mode: str = "parallel", background=None) -> tuple[float, float | None, dict]:
    """(axis column at the detector's middle row, roll in degrees or None, report) from every
    estimator that applies (module doc). ``proj`` (n_views, rows, columns) line integrals with the
    air at 0; ``background`` as for :func:`com_axis`."""
    p = np.asarray(proj, np.float64)
    theta = np.asarray(angles_rad, np.float64).reshape(-1)
    if theta.size != p.shape[0]:
        raise AxisError(f"{theta.size} angles for {p.shape[0]} views")
    n_rows = p.shape[1]
    cone = mode == "cone"
    if cone:  # the central rows only, where cone-beam views are nearly parallel
        mid = (n_rows - 1) / 2.0
        keep = np.arange(int(np.floor(mid)) - 1, int(np.ceil(mid)) + 2)
        keep = keep[(keep >= 0) & (keep < n_rows)]
        p_est = p[:, keep]  # symmetric about the middle row
    else:
        p_est = p
    estimates = {
        "pair": pair_axis(p_est, theta, fit_roll=not cone),
        "sinogram": sinogram_axis(p_est, theta),
        "com": com_axis(p_est, theta, background),
    }
    for name, e in estimates.items():
        e["name"] = NAMES[name]
        if e["available"]:
            e.setdefault("counted", True)
            if cone:
                e["note"] = "approximate in cone beam (central rows)"
    counted = [k for k in ESTIMATORS if estimates[k]["available"] and estimates[k]["counted"]]
    if not counted:
        counted_or_any = [k for k in ESTIMATORS if estimates[k]["available"]]
        if not counted_or_any:
            why = "; ".join(f"{NAMES[k]}: {estimates[k]['why']}" for k in ESTIMATORS)
            raise AxisError(f"the rotation axis cannot be found ({why}); give it (--centre COLUMN)")
        counted = counted_or_any
    cols = {k: estimates[k]["column"] for k in counted}
    spread = float(max(cols.values()) - min(cols.values())) if len(cols) > 1 else 0.0
    agree = spread <= AGREE_PX
    chosen = counted[0]
    why = "the first available of pair, sinogram, centre of mass"
    if not agree and len(counted) == 3:
        pairs_ok = [(a, b) for ai, a in enumerate(counted) for b in counted[ai + 1:]
                    if abs(cols[a] - cols[b]) <= AGREE_PX]
        if len(pairs_ok) == 1:
            chosen = pairs_ok[0][0]
            why = f"{NAMES[pairs_ok[0][0]]} and {NAMES[pairs_ok[0][1]]} agree, the third does not"
    column = cols[chosen]
    tilt = estimates["pair"].get("tilt_deg") if estimates["pair"]["available"] else None
    report = {"column": column, "method": NAMES[chosen], "chosen": chosen, "why": why,
              "estimates": estimates, "counted": counted, "spread_pixels": spread, "agree": agree}
    if not agree:
        figures = ", ".join(f"{NAMES[k]} {cols[k]:.2f}" for k in counted)
        report["warning"] = (f"the axis estimators disagree by {spread:.2f} px ({figures}); chose {column:.2f} "
                             f"({NAMES[chosen]}: {why}). Check a reconstruction and give the axis with "
                             "--centre COLUMN if this is wrong")
    return column, tilt, report
