"""The grids a simulated scan is made on: the reconstruction grid a user asks for, and the finer
grid its projections come from.

Projecting a truth with the same Joseph projector on the same grid that SART and FDK then invert
(R2-Gaussian's protocol, ``"same"``) is the "inverse crime": the classical methods meet data that
their own discrete model explains exactly, and look better than on a real scan. The ``"fine"``
protocol, the default for new scans, projects a volume at least twice as fine along every axis as
the reconstruction grid: the input itself when it is that fine already (a clinical CT simulated
onto a coarser ``--grid``), otherwise the input refined by linear interpolation. Both grids cover
the same box (the input's field of view), so the truth and the projections describe one object.
"""
from __future__ import annotations

import math

import numpy as np

from clgs.errors import InputError

PROTOCOLS = ("fine", "same")
#: how much finer than the reconstruction grid the "fine" protocol projects, per axis
FINE_FACTOR = 2

__all__ = ["PROTOCOLS", "FINE_FACTOR", "resample_box", "projection_volume", "parse_grid", "fine_bytes"]


def parse_grid(value, like=None) -> tuple | None:
    """``N`` or ``NZ,NY,NX`` voxels -> a (Z, Y, X) shape, or None for "the input's own grid"."""
    if value is None or str(value).strip() == "":
        return None
    parts = [p.strip() for p in str(value).split(",")]
    try:
        n = [int(p) for p in parts]
    except ValueError:
        raise InputError(f"grid {value!r}: give N or NZ,NY,NX voxels (whole numbers)") from None
    if len(n) == 1:
        n = n * 3
    if len(n) != 3 or min(n) < 1:
        raise InputError(f"grid {value!r}: give N or NZ,NY,NX voxels, each at least 1")
    return tuple(n)


def resample_box(volume: np.ndarray, shape) -> np.ndarray:
    """``volume`` on a grid of ``shape`` voxels covering the same box (linear interpolation; area
    averaging when a side shrinks, so fine detail is not aliased into the coarser grid)."""
    from skimage.transform import resize

    shape = tuple(int(s) for s in shape)
    vol = np.asarray(volume, np.float32)
    if vol.shape == shape:
        return vol
    shrink = any(t < s for t, s in zip(shape, vol.shape))
    out = resize(vol, shape, order=1, mode="edge", anti_aliasing=shrink, preserve_range=True)
    return np.ascontiguousarray(out, np.float32)


def projection_volume(volume: np.ndarray, recon_shape, protocol: str = "fine") -> np.ndarray:
    """The volume the projections are made from: the truth on the reconstruction grid (``same``), or
    (``fine``) the input on a grid at least :data:`FINE_FACTOR` times finer than ``recon_shape``
    along every axis, covering the same box."""
    if protocol not in PROTOCOLS:
        raise InputError(f"simulation protocol {protocol!r}: choose one of {', '.join(PROTOCOLS)}")
    vol = np.asarray(volume, np.float32)
    recon_shape = tuple(int(s) for s in recon_shape)
    if protocol == "same":
        return resample_box(vol, recon_shape)
    # a side already fine enough keeps the input's own samples (no interpolation along it)
    fine = _fine_shape(recon_shape, vol.shape)
    return resample_box(vol, fine)


def fine_bytes(recon_shape, input_shape) -> float:
    """Bytes of the ``fine`` projection volume (float32), for memory checks before any work."""
    return 4.0 * math.prod(_fine_shape(recon_shape, input_shape))


def _fine_shape(recon_shape, input_shape) -> tuple:
    return tuple(int(n_in) if n_in >= FINE_FACTOR * n else FINE_FACTOR * int(n)
                 for n_in, n in zip(input_shape, recon_shape))
