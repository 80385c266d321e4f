"""Side by side in one process: each speed step of the shape-guided iteration against the code
before it, on the same trainer, in alternating blocks of iterations (``clgs bench train --method
shape --alternate N``). The machine's load drifts; alternating blocks share it, so the ratios
hold where absolute times from different runs would not. Each step is switched here, by putting
the old path back where the library calls the new one; the library itself has no switch for it."""
from __future__ import annotations

import time
from contextlib import contextmanager

# ---------------------------------------------------------------------- the old paths


def grid_sample_at_ref_points(self, field):
    """``ShapeGuidedSet._at_ref_points`` before the fixed-point sampler: grid_sample every time."""
    return self.shape_model.sample(field, self.p_ref)


def grid_sample_centres_mm(self, u=None):
    """``ShapeGuidedSet._model_centres_mm`` before the fixed-point sampler: exact every iteration
    (no linearisation in alpha), through grid_sample."""
    u = self.displacement() if u is None else u
    return self.p_ref + self.shape_model.sample(u, self.p_ref)


def two_atlas_passes(self, x_t):
    """``DensityPrior._atlas_at`` before the one-pass read: the mean and the variance apart."""
    return self.atlas.mean_at(x_t), self.atlas.var_at(x_t)


_LIBRARY: dict = {}  # (class, attribute) -> the library's own, taken before the first switch


def _put(cls, name: str, old, on: bool) -> None:
    new = _LIBRARY.setdefault((cls, name), cls.__dict__[name])
    setattr(cls, name, new if on else old)


def steps() -> dict:
    """name -> a function that turns the step on (True) or off (False, the code before it)."""
    import numpy as np

    from clgs.ops import field_sampler, sorting, voxelizer
    from clgs.shape.gaussian_set import ShapeGuidedSet
    from clgs.shape.priors import DensityPrior

    def numpy_order(keys):
        return np.argsort(np.asarray(keys), kind="stable")

    def argsort(on):  # the cell orders of the field sampler and the voxelizer
        field_sampler.stable_order = voxelizer.stable_order = sorting.stable_order if on else numpy_order

    def fixed_points(on):
        _put(ShapeGuidedSet, "_at_ref_points", grid_sample_at_ref_points, on)
        _put(ShapeGuidedSet, "_model_centres_mm", grid_sample_centres_mm, on)

    tol = ShapeGuidedSet.LINEAR_TOL if ShapeGuidedSet.LINEAR_TOL is not None else 0.05

    def parallel_bins(on):
        voxelizer._SMALL_PAIRS = (1 << 19) if on else (1 << 22)

    def atlas(on):
        _put(DensityPrior, "_atlas_at", two_atlas_passes, on)

    def linear(on):
        ShapeGuidedSet.LINEAR_TOL = tol if on else None

    return {
        "cell order by a sort of packed keys (field sampler, voxelizer)": argsort,
        "centres by a sparse matrix built once": fixed_points,
        "deformation linearised in alpha between refreshes": linear,
        "atlas mean and variance in one pass": atlas,
        "density sub-grid binned by the parallel counting sort": parallel_bins,
    }


@contextmanager
def all_steps(on: bool):
    """Every step on or off inside the block; on again after it."""
    switches = steps()
    for f in switches.values():
        f(on)
    try:
        yield
    finally:
        for f in switches.values():
            f(True)


def _block(trainer, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        trainer.step()
    return time.perf_counter() - t0


def alternate(trainer, rounds: int, block: int = 5) -> list:
    """(name, ms per iteration before, after, median over the pairs of before / after) for each
    step alone (the others on) and for all of them together; ``rounds`` pairs of ``block``
    iterations each, the order of the pair swapped every round. The median of the pairs' ratios
    is what to quote: one pair that another job's burst hit does not move it."""
    import statistics

    import torch

    threads = torch.get_num_threads()
    if trainer.torch_threads:
        torch.set_num_threads(trainer.torch_threads)
    rows = []
    try:
        cases = [(name, {name}) for name in steps()] + [("all of them", set(steps()))]
        for name, off in cases:
            switches = steps()
            t = {False: 0.0, True: 0.0}
            ratios = []
            for r in range(rounds):
                pair = {}
                for on in ((False, True) if r % 2 == 0 else (True, False)):
                    for k, f in switches.items():
                        f(on or k not in off)
                    pair[on] = _block(trainer, block)
                    t[on] += pair[on]
                ratios.append(pair[False] / pair[True])
            for f in switches.values():
                f(True)
            n = rounds * block
            rows.append((name, t[False] / n * 1e3, t[True] / n * 1e3, statistics.median(ratios)))
    finally:
        torch.set_num_threads(threads)
        for f in steps().values():
            f(True)
    return rows
