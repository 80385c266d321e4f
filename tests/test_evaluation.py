"""The outer-bone mask behind the surface distance of reconstructions."""
import numpy as np
import pytest
from scipy import ndimage

from clgs.anatomy.evaluation import bone_mask


def test_bone_mask_keeps_every_fragment_fills_cavities_and_drops_speckles():
    vol = np.zeros((20, 20, 40), np.float32)
    vol[5:15, 5:15, 2:18] = 1.0  # a fragment with a cavity
    vol[8:12, 8:12, 6:14] = 0.0
    vol[5:15, 5:15, 22:36] = 1.0  # the other fragment, a little smaller
    vol[1, 1, 38] = 1.0  # a speckle
    mask = bone_mask(vol, 0.5)
    assert mask[10, 10, 10]  # the cavity is filled
    assert mask[10, 10, 30]  # the second fragment is kept
    assert not mask[1, 1, 38]  # the speckle is not
    assert int(mask.sum()) == 10 * 10 * 16 + 10 * 10 * 14
    only_largest = bone_mask(vol, 0.5, min_piece=1.0)
    assert not only_largest[10, 10, 30] and only_largest[10, 10, 10]


# ------------------------------------------------------------------------------ gaps in the bone's wall
def _hollow_cylinder(n=40, outer=12.0, inner=8.0, end=7):
    """A closed hollow cylinder along axis 0 (a bone's shaft with its cavity; ends capped), bool."""
    z, y, x = np.mgrid[:n, :n, :n]
    r = np.hypot(y - (n - 1) / 2, x - (n - 1) / 2)
    tube = (r < outer) & (z >= 4) & (z < n - 4)
    tube[(r < inner) & (z >= end) & (z < n - end)] = False
    return tube


def _drilled(tube, width, depth=8):
    """The tube with a square hole ``width`` voxels wide through its wall along +x, from ``depth``
    voxels off the axis outwards."""
    t = tube.copy()
    c = tube.shape[1] // 2 - 2
    t[c:c + width, c:c + width, tube.shape[2] // 2 + depth:] = False
    return t


def _surface(mask):
    import trimesh

    from clgs.mesh.surface import surface_from_volume

    m = surface_from_volume(mask)
    return trimesh.Trimesh(m.vertices, m.faces, process=False)


def test_a_hole_through_the_wall_is_sealed_and_the_outer_surface_is_the_intact_bones():
    """Known answer: a hollow cylinder drilled through its wall (4 voxels wide, the wall 4 thick).
    Without a closing the cavity reaches the outside and is not filled: the mask is the wall, its
    surface holds the cavity's walls too (trimesh: 1.4 times the intact solid's area). A closing
    of up to 3 voxels seals the hole: the solid is the intact tube's, filled, to within a few voxels
    at the hole's mouth, and its surface lies on the intact one's."""
    from clgs.anatomy.evaluation import solid_bone

    tube = _hollow_cylinder()
    intact = ndimage.binary_fill_holes(tube)
    drilled = _drilled(tube, 4).astype(np.float32)
    open_, r0 = solid_bone(drilled, 0.5)
    sealed, r3 = solid_bone(drilled, 0.5, closing=3)
    assert r0 == 0 and r3 == 3
    assert open_.sum() < 0.7 * intact.sum()  # the wall alone
    assert abs(int(sealed.sum()) - int(intact.sum())) < 0.002 * intact.sum()
    assert (sealed ^ intact).sum() < 40
    s_open, s_sealed, s_intact = _surface(open_), _surface(sealed), _surface(intact)
    assert s_open.area > 1.4 * s_intact.area
    assert s_sealed.area == pytest.approx(s_intact.area, rel=0.01)
    import trimesh

    _, d, _ = trimesh.proximity.closest_point(s_intact, s_sealed.vertices)
    assert d.mean() < 0.02 and d.max() <= 1.0 + 1e-9  # a one-voxel dimple at the mouth


@pytest.mark.parametrize("width, radius", [(1, 1), (2, 1), (3, 2), (4, 2), (5, 3), (6, 3)])
def test_the_closing_is_the_smallest_that_seals_the_hole(width, radius):
    """A thick-walled tube (the wall 8 voxels) drilled by a hole 1 to 6 voxels wide: the radius used
    is the smallest ball that seals it (a ball of r seals holes up to about 2 r wide), found even
    where the smaller balls before it grow the solid by under 1 % (they only fill creases), and the
    solid is the intact tube's but for the hole's mouth."""
    from clgs.anatomy.evaluation import solid_bone

    tube = _hollow_cylinder(n=72, outer=24.0, inner=16.0, end=10)
    intact = int(ndimage.binary_fill_holes(tube).sum())
    sealed, used = solid_bone(_drilled(tube, width, depth=12).astype(np.float32), 0.5, closing=4)
    assert used == radius
    assert -80 <= int(sealed.sum()) - intact <= 0


def test_the_closing_is_scipys_binary_closing_by_a_ball():
    """Reference: the distance-transform closings on the bone's bounding box equal scipy's
    binary_closing by a ball (offsets with dz^2 + dy^2 + dx^2 <= r^2) of the padded mask, for radii
    1-4, on random masks, bone at the grid's edge included."""
    from clgs.anatomy.evaluation import _closings

    rng = np.random.default_rng(0)
    for trial in range(4):
        m = rng.random((22, 26, 18)) > (0.7 if trial % 2 else 0.5)
        m = ndimage.binary_opening(m) if trial >= 2 else m
        m[0] |= trial == 3
        for r, got in enumerate(_closings(m, 4), start=1):
            g = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
            p = r + 1
            want = ndimage.binary_closing(np.pad(m, p), (g ** 2).sum(0) <= r * r)[p:-p, p:-p, p:-p]
            assert np.array_equal(got, want), (trial, r)


def test_a_bone_without_a_hole_is_left_exactly_as_it_was():
    from clgs.anatomy.evaluation import bone_mask, solid_bone

    tube = _hollow_cylinder().astype(np.float32)
    mask, used = solid_bone(tube, 0.5, closing=3)
    assert used == 0 and np.array_equal(mask, bone_mask(tube, 0.5))


def test_without_a_closing_bones_a_few_voxels_apart_stay_two():
    """Why the closing is the anatomy's to ask for: two bones 2 voxels apart (a joint, ribs) stay two
    without it and become one with it, their gap filled."""
    from clgs.anatomy.bone_level import BoneLevel
    from clgs.anatomy.evaluation import bone_mask

    vol = np.zeros((30, 30, 40), np.float32)
    vol[5:25, 5:25, 4:18] = 1.0
    vol[5:25, 5:25, 20:36] = 1.0
    assert ndimage.label(bone_mask(vol, 0.5))[1] == 2
    assert BoneLevel(0.5, "user").closing == 0  # a level with no anatomy closes nothing
    joined = bone_mask(vol, 0.5, closing=3)
    assert ndimage.label(joined)[1] == 1 and joined[15, 15, 18:20].all()


def test_a_scene_closing_is_a_whole_number_of_voxels_within_bounds():
    from clgs.anatomy.bone_level import BoneLevel
    from clgs.anatomy.record import MAX_CLOSING, Scene, SceneError

    assert Scene(surface_closing=3).surface_closing == 3 and Scene().surface_closing is None
    for bad in (-1, 1.5, MAX_CLOSING + 1, True, float("nan")):
        with pytest.raises(SceneError, match="surface_closing"):
            Scene(surface_closing=bad)
    with pytest.raises(ValueError, match="whole number"):
        BoneLevel(0.03, "user", closing=-2)
