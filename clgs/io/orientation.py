"""A volume file's array order and clgs's working order, and the moves between them.

clgs computes on (Z, Y, X) arrays whose axes grow along +z, +y, +x of the world (RAS+: in NIfTI
terms the array ``volume.T`` has axis codes ``"RAS"``). A file may store its array in any other
axis order and direction: dcm2niix writes ``"LAS"``, a DICOM axial series reads as ``"LPS"``,
some files permute the axes (``"PSR"``). The codes are nibabel's (``nibabel.aff2axcodes``): the
world direction each of the file's array axes (i, j, k) grows towards.

``to_working`` brings a file's array (indexed as the file indexes it, reversed to (k, j, i) as a
clgs ``.npy`` is) into the working order; ``to_file`` takes it back, and ``file_affine`` gives
the file's voxel-to-world matrix for a working grid. Flips and axis swaps only: values are never
interpolated, so a round trip gives the same array, bit for bit.
"""
from __future__ import annotations

import numpy as np

from clgs.geometry import check_orientation

__all__ = ["WORKING", "axis_codes", "to_working", "to_file", "file_affine"]

WORKING = "RAS"


def axis_codes(affine) -> str:
    """The axis codes (e.g. ``"LAS"``) of a voxel-to-world (RAS, mm) affine."""
    from nibabel.orientations import aff2axcodes

    return "".join(aff2axcodes(np.asarray(affine, float)))


def _transform(src: str, dst: str):
    from nibabel.orientations import axcodes2ornt, ornt_transform

    return ornt_transform(axcodes2ornt(check_orientation(src)), axcodes2ornt(check_orientation(dst)))


def to_working(array_kji, codes: str) -> np.ndarray:
    """A file's array, its axes reversed to (k, j, i) (the order of a clgs ``.npy``), in clgs's
    (Z, Y, X) RAS+ order. ``codes``: the file's axis codes."""
    from nibabel.orientations import apply_orientation

    codes = check_orientation(codes)
    arr = np.asarray(array_kji)
    if codes == WORKING:
        return arr
    return np.ascontiguousarray(apply_orientation(arr.T, _transform(codes, WORKING)).T)


def to_file(volume_zyx, codes: str) -> np.ndarray:
    """The inverse of :func:`to_working`: a (Z, Y, X) RAS+ array in the order of a file with axis
    codes ``codes``, still reversed to (k, j, i)."""
    from nibabel.orientations import apply_orientation

    codes = check_orientation(codes)
    arr = np.asarray(volume_zyx)
    if codes == WORKING:
        return arr
    return np.ascontiguousarray(apply_orientation(arr.T, _transform(WORKING, codes)).T)


def file_affine(spacing_zyx, origin_xyz, shape_zyx, codes: str) -> np.ndarray:
    """The 4x4 voxel (i, j, k) to world (x, y, z, mm) matrix of the file that stores the working
    grid (spacing (dZ, dY, dX), ``origin_xyz`` the centre of working voxel [0, 0, 0], ``shape_zyx``)
    in the order ``codes``: the same voxels in the same places, indexed the file's way."""
    from nibabel.orientations import inv_ornt_aff

    aff = np.eye(4)
    aff[0, 0], aff[1, 1], aff[2, 2] = np.asarray(spacing_zyx, float)[::-1]
    aff[:3, 3] = np.asarray(origin_xyz, float)
    codes = check_orientation(codes)
    if codes == WORKING:
        return aff
    return aff @ inv_ornt_aff(_transform(WORKING, codes), tuple(int(n) for n in shape_zyx[::-1]))
