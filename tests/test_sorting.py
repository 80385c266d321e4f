"""clgs.ops.sorting.stable_order gives exactly NumPy's stable argsort."""
import numpy as np
import pytest

from clgs.ops import sorting


@pytest.mark.parametrize("n,top", [(0, 1), (1, 1), (7, 0), (1000, 3), (80_000, 75_000), (5000, 2**40)])
def test_same_order_as_the_stable_argsort(n, top):
    rng = np.random.default_rng(n)
    keys = rng.integers(0, top + 1, n)
    for k in (keys, keys.astype(np.int32) if top < 2**31 else keys, np.sort(keys)):
        got = sorting.stable_order(k)
        assert np.array_equal(got, np.argsort(k, kind="stable"))


def test_nearly_sorted_cells():
    # displaced grid points: each cell's points nearly in order, many ties
    rng = np.random.default_rng(1)
    keys = np.clip(np.arange(50_000) // 2 + rng.integers(-3, 4, 50_000), 0, None).astype(np.int32)
    assert np.array_equal(sorting.stable_order(keys), np.argsort(keys, kind="stable"))


def test_the_benchmark_switch_lives_in_the_benchmark():
    """``clgs bench train --alternate`` swaps NumPy's argsort in and out from clgs.bench; the
    library keeps no switch for it."""
    from clgs.bench.switches import steps
    from clgs.ops import field_sampler, voxelizer

    assert not hasattr(sorting, "USE_ARGSORT")
    step = steps()["cell order by a sort of packed keys (field sampler, voxelizer)"]
    step(False)
    try:
        assert field_sampler.stable_order is not sorting.stable_order
        keys = np.array([3, 1, 2, 1, 0])
        assert np.array_equal(voxelizer.stable_order(keys), np.argsort(keys, kind="stable"))
    finally:
        step(True)
    assert field_sampler.stable_order is sorting.stable_order and voxelizer.stable_order is sorting.stable_order


def test_negative_keys_fall_back_to_the_argsort():
    keys = np.array([3, -1, 2, -1, 0])
    assert np.array_equal(sorting.stable_order(keys), np.argsort(keys, kind="stable"))
