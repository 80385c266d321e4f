"""The outer-bone mask behind the surface distance of reconstructions."""
import numpy as np

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
