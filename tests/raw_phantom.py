"""Raw counts of an analytic phantom (balls and Gaussian blobs) on a parallel-beam detector with a
known axis column, roll, beam and detector faults: the known answers for the import's calibration.

Every pixel's line integral is exact (the ray's distance to each ball's or blob's centre), along the
rays clgs's own geometry gives each pixel (``Geometry.rays``), so the roll and the axis follow
clgs's conventions by construction."""
from __future__ import annotations

import numpy as np

from clgs.geometry import Geometry

# (x, y, z) mm, radius or sigma mm, density per mm; about 24 mm around the axis
BALLS = [((6.0, -4.0, 0.0), 14.0, 0.02), ((-9.0, 8.0, 2.0), 6.0, 0.05), ((10.0, 9.0, -3.0), 4.0, 0.08),
         ((-4.0, -12.0, 3.0), 3.0, 0.06)]
BLOBS = [((-12.0, -3.0, -2.0), 3.0, 0.04), ((3.0, 14.0, 1.0), 2.5, 0.05)]


def rolled_geometry(n_views, rows, cols, axis_column, roll_deg=0.0, arc_deg=180.0, endpoint=False):
    """A parallel-beam vector geometry (1 mm pixels): the axis meets the middle row at
    ``axis_column``, the detector turned by ``roll_deg`` in its plane (u towards v)."""
    angles = np.deg2rad(np.linspace(0.0, arc_deg, n_views, endpoint=endpoint))
    base = Geometry(mode="parallel", DSD=1500.0, DSO=1000.0, nDetector=(rows, cols), dDetector=(1.0, 1.0),
                    nVoxel=(rows, cols, cols), dVoxel=(1.0, 1.0, 1.0), offDetector=(0.0, 0.0), angles=angles)
    vec = base.frame_vectors()
    g = np.deg2rad(roll_deg)
    e_u, e_v = vec[:, 6:9].copy(), vec[:, 9:12].copy()
    vec[:, 6:9] = np.cos(g) * e_u + np.sin(g) * e_v
    vec[:, 9:12] = -np.sin(g) * e_u + np.cos(g) * e_v
    vec[:, 3:6] += ((cols - 1) / 2.0 - axis_column) * np.cos(g) * e_u
    return Geometry.from_vectors(vec, (rows, cols), (rows, cols, cols), (1.0, 1.0, 1.0), mode="parallel"), angles


def line_integrals(geo, scale=1.0, shift=(0.0, 0.0, 0.0)):
    """(n_views, rows, cols) exact line integrals of the phantom (moved by ``shift`` mm, sizes times
    ``scale``)."""
    out = np.zeros((geo.n_views,) + tuple(geo.nDetector))
    for v in range(geo.n_views):
        origin, direction = geo.rays(v, scene=False)
        for (c, r, rho), ball in [(b, True) for b in BALLS] + [(b, False) for b in BLOBS]:
            q = (np.asarray(c) + np.asarray(shift)) * scale
            d = origin - q
            t = np.sum(d * direction, axis=-1)
            dist2 = np.sum(d * d, axis=-1) - t * t
            if ball:
                out[v] += 2 * rho * np.sqrt(np.clip((r * scale) ** 2 - dist2, 0.0, None))
            else:
                s = r * scale
                out[v] += rho * s * np.sqrt(2 * np.pi) * np.exp(-dist2 / (2 * s * s))
    return out


def raw_counts(p, beam=None, seed=0, i0=2e4, stripes=None, noise=True):
    """(counts, flats, darks) float32: ``p`` line integrals seen through a detector with a
    structured gain and dark; ``beam`` (n_views,) the beam during each projection relative to the
    flat field's (a uniform background is ``beam < 1``); ``stripes`` (columns,) a gain error of the
    projections that the flat does not have (rings)."""
    rng = np.random.default_rng(seed)
    n, rows, cols = p.shape
    gain = rng.uniform(0.85, 1.15, (rows, cols))
    dark = rng.uniform(95.0, 105.0, (rows, cols))
    beam = np.ones(n) if beam is None else np.asarray(beam, np.float64)
    proj_gain = gain * (1.0 if stripes is None else (1.0 + np.asarray(stripes))[None, :])
    mean = dark + i0 * proj_gain * beam[:, None, None] * np.exp(-p)
    counts = rng.poisson(mean).astype(np.float64) if noise else mean
    flats = np.stack([dark + i0 * gain] * 3)
    darks = np.stack([dark] * 2)
    return counts.astype(np.float32), flats.astype(np.float32), darks.astype(np.float32)
