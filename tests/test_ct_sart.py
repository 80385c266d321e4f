"""SART / OS-SART: residual decreases, non-negativity, reproducibility, bad input."""
import numpy as np
import pytest

from clgs.ct import phantoms as ph
from clgs.ct.sart import sart, subsets_of
from clgs.geometry import Geometry
from clgs.ops.ct_projector import CTProjector

OBJ = [ph.ball((2.0, -1.0, 1.0), 9.0, 0.02), ph.ball((-3.0, 2.0, 0.0), 4.0, 0.01)]


def geom(mode="cone", n_views=12):
    return Geometry(DSD=300.0, DSO=200.0, nDetector=(36, 44), dDetector=(1.2, 1.2), nVoxel=(24, 32, 30),
                    dVoxel=(1.0, 1.0, 1.0), angles=np.linspace(0, np.pi, n_views, endpoint=False),
                    offOrigin=(0.5, -0.5, 0.0), mode=mode)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
@pytest.mark.parametrize("subsets", [1, 4])
def test_residual_decreases_monotonically(mode, subsets):
    g = geom(mode)
    P = CTProjector(g)
    truth = ph.voxelize(OBJ, g, 2)
    b = P.forward(truth)
    res, err = [], []

    def log(it, x):
        res.append(float(np.linalg.norm(P.forward(x) - b)))
        err.append(float(np.linalg.norm(x - truth)))

    x = sart(b, g, n_iter=6, subsets=subsets, callback=log, projector=P, order="ordered")
    assert len(res) == 6
    assert np.all(np.diff(res) < 0), res
    assert res[-1] < 0.3 * np.linalg.norm(b)
    assert err[-1] < 0.8 * err[0] and err[0] < np.linalg.norm(truth)
    assert x.dtype == np.float32 and x.min() >= 0


def test_os_sart_converges_faster_per_iteration():
    g = geom("cone")
    P = CTProjector(g)
    b = P.forward(ph.voxelize(OBJ, g, 2))
    r1 = np.linalg.norm(P.forward(sart(b, g, n_iter=3, projector=P)) - b)
    r4 = np.linalg.norm(P.forward(sart(b, g, n_iter=3, subsets=4, projector=P)) - b)
    assert r4 < 0.7 * r1


def test_nonnegativity_is_enforced():
    """Noisy data drive unconstrained SART below zero in the empty background; nonneg stops it."""
    g = geom("parallel")
    P = CTProjector(g)
    b = P.forward(ph.voxelize(OBJ, g, 2))
    b = b + np.random.default_rng(0).normal(0, 0.05, b.shape).astype(np.float32)
    free = sart(b, g, n_iter=3, subsets=4, nonneg=False, projector=P)
    assert free.min() < -1e-3
    pos = sart(b, g, n_iter=3, subsets=4, nonneg=True, projector=P, x0=-np.ones(g.nVoxel))
    assert pos.min() >= 0.0


def test_subsets_interleave_the_arc():
    g = geom(n_views=10)
    groups = subsets_of(g, 3)
    assert sorted(np.concatenate(groups).tolist()) == list(range(10))
    assert [len(s) for s in groups] == [4, 3, 3]
    np.testing.assert_array_equal(groups[0], [0, 3, 6, 9])
    with pytest.raises(ValueError, match="subsets"):
        subsets_of(g, 11)


def test_random_order_is_seeded():
    g = geom("cone", n_views=8)
    P = CTProjector(g)
    b = P.forward(ph.voxelize(OBJ, g, 1))
    a = sart(b, g, n_iter=2, subsets=4, seed=3, projector=P)
    assert a.tobytes() == sart(b, g, n_iter=2, subsets=4, seed=3, projector=P).tobytes()
    assert a.tobytes() != sart(b, g, n_iter=2, subsets=4, seed=4, projector=P).tobytes()


def test_bad_input_is_a_clear_error():
    g = geom(n_views=4)
    b = np.zeros(g.projection_shape, np.float32)
    bad = b.copy()
    bad[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        sart(bad, g, n_iter=1)
    with pytest.raises(ValueError, match="at least one view"):
        sart(np.zeros((0, 36, 44)), g, n_iter=1)
    with pytest.raises(ValueError, match="relaxation"):
        sart(b, g, n_iter=1, relaxation=2.5)
    with pytest.raises(ValueError, match="x0"):
        sart(b, g, n_iter=1, x0=np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="order"):
        sart(b, g, n_iter=1, order="shuffled")
