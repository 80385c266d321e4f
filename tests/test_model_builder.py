"""Model builder: PCA of velocity fields, density atlas, one file, caching and resuming."""
import os

import numpy as np
import pytest
import torch

from clgs.shape.builder import build_model, population_pca
from clgs.shape.model import load_model, read_metadata
from clgs.shape.template import Subject, Template, box_grid, grid_points, mesh_from_sdf

FAST = {"levels": [8, 0], "iterations": [15, 15]}
MAX_CELLS = 14


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# grid of the CT volumes and the template
SHAPE, SP, ORG = box_grid((-30, -20, -18), (30, 20, 18), spacing=3.0)


def _ellipsoid(axes, density=0.03, sid="s"):
    a = np.asarray(axes, float)
    shape, sp, org = box_grid(-a - 3, a + 3, spacing=1.2)
    p = grid_points(shape, sp, org)
    v, f = mesh_from_sdf((np.linalg.norm(p / a, axis=-1) - 1) * a.min(), sp, org)
    q = grid_points(SHAPE, SP, ORG)
    ct = (np.linalg.norm(q / a, axis=-1) < 1).astype(np.float32) * density
    return Subject(sid, v, f, volume=ct, spacing=SP, origin=ORG)


def _template():
    s = _ellipsoid((20, 12, 10))
    return Template.from_mesh(s.vertices, s.faces, spacing=SP, shape=SHAPE, origin=ORG, name="ellipsoid")


def _population(n=5, seed=0):
    rng = np.random.default_rng(seed)
    return [_ellipsoid((20 + 3 * rng.standard_normal(), 12 + 1.5 * rng.standard_normal(),
                        10 + 1.0 * rng.standard_normal()), 0.03, f"p{i}") for i in range(n)]


def _counting(subjects, log):
    def loader(s):
        def load():
            log.append(s.id)
            return s
        return load
    return {s.id: loader(s) for s in subjects}


# ------------------------------------------------------------------------------------------ PCA
def test_population_pca_keeps_variance_and_reconstructs(rng):
    n, d = 8, 50
    basis = np.linalg.qr(rng.standard_normal((d, 3)))[0].T
    X = (rng.standard_normal((n, 3)) * [10.0, 3.0, 0.3]) @ basis + rng.standard_normal(d)
    for target in (0.5, 0.95, 0.999):
        mean, modes, sigma, kept, spectrum = population_pca(X, variance=target)
        frac = np.cumsum(spectrum) / spectrum.sum()
        m = len(modes)
        assert kept == pytest.approx(frac[m - 1]) and kept >= target  # enough modes ...
        assert m == 1 or frac[m - 2] < target  # ... and no more than needed
    mean, modes, sigma, kept, _ = population_pca(X, n_modes=3)
    np.testing.assert_allclose(modes @ modes.T, np.eye(3), atol=1e-10)
    scores = (X - mean) @ modes.T
    np.testing.assert_allclose(scores.std(0, ddof=1), sigma, rtol=1e-10)
    np.testing.assert_allclose(mean + scores @ modes, X, atol=1e-9)  # all variation kept: exact
    assert kept == pytest.approx(1.0)
    with pytest.raises(ValueError):
        population_pca(X[:1])


# ------------------------------------------------------------------------------------------ build
def test_build_model_pca_reconstructs_its_training_subjects(tmp_path):
    template, subjects = _template(), _population(5)
    out = tmp_path / "model.npz"
    build_model(template, subjects, out, n_modes=4, max_cells=MAX_CELLS, registration=FAST, keep_cache=True,
                progress=False)
    sm, atlas = load_model(out)
    meta = read_metadata(out)
    assert meta["population"] == [s.id for s in subjects] and sm.n_modes == 4
    assert meta["variance_kept"] == pytest.approx(1.0)
    assert set(meta["residuals"]) == {s.id for s in subjects}
    assert all(r["surface_mean_mm"] < 1.0 and r["dice"] > 0.9 for r in meta["residuals"].values())
    cached = sorted(os.listdir(str(out) + ".cache"))
    assert len(cached) == 5
    largest = 0.0
    for s in subjects:
        (name,) = [c for c in cached if c.startswith(s.id + "-")]
        with np.load(os.path.join(str(out) + ".cache", name), allow_pickle=False) as z:
            v = torch.as_tensor(z["velocity"])
        largest = max(largest, float(v.abs().max()))
        recon = sm.velocity(sm.project(v))
        assert float((recon - v).abs().max()) < 1e-4 * float(v.abs().max()) + 1e-5
    assert largest > 2.0  # the population really varies (mm)
    # the atlas: same densities everywhere, so the mean is bone density inside and no variance deep inside
    assert atlas.shape == template.shape
    inside = template.sdf < -4.0
    np.testing.assert_allclose(atlas.mean[inside], 0.03, rtol=1e-4)
    assert atlas.var[inside].max() < 1e-10


def test_atlas_of_identical_subjects_and_density_statistics(tmp_path):
    template = _template()
    same = [_ellipsoid((20, 12, 10), 0.03, f"same{i}") for i in range(3)]
    out = tmp_path / "same.npz"
    build_model(template, same, out, max_cells=MAX_CELLS, registration=FAST, progress=False)
    sm, atlas = load_model(out)
    assert atlas.var.max() == 0.0
    assert sm.n_modes == 0  # no shape variation at all
    assert np.isfinite(sm.displacement().numpy()).all()
    # identical shapes with different densities: the atlas is their per-voxel mean and variance
    dens = np.array([0.02, 0.03, 0.05])
    varied = [_ellipsoid((20, 12, 10), d, f"d{i}") for i, d in enumerate(dens)]
    out2 = tmp_path / "dens.npz"
    build_model(template, varied, out2, max_cells=MAX_CELLS, registration=FAST, progress=False)
    _, atlas2 = load_model(out2)
    shape_map = atlas2.mean / dens.mean()  # the (common) warped bone indicator
    np.testing.assert_allclose(atlas2.var, dens.var() * shape_map ** 2, atol=1e-8)
    assert shape_map.max() == pytest.approx(1.0, abs=1e-4)


def test_atlas_is_not_darkened_where_a_ct_grid_ends(tmp_path):
    """The same limb scanned on grids shifted by one voxel along z: template points past a CT's
    last slice take its border value, so the atlas stays the limb's value (0.02) with a small
    variance in the border slices, instead of the average with air (mean 0.01, variance 1e-4)."""
    template = _template()
    q = grid_points(SHAPE, SP, ORG)
    subjects = []
    for i, dz in enumerate((-SP[0], 0.0, SP[0])):
        org = (ORG[0] + dz, ORG[1], ORG[2])
        p = grid_points(SHAPE, SP, org)
        ct = (0.02 + 0.03 * (np.linalg.norm(p / np.array([20.0, 12.0, 10.0]), axis=-1) < 1)).astype(np.float32)
        s = _ellipsoid((20, 12, 10), 0.03, f"shift{i}")
        subjects.append(Subject(s.id, s.vertices, s.faces, volume=ct, spacing=SP, origin=org))
    out = tmp_path / "shift.npz"
    build_model(template, subjects, out, max_cells=MAX_CELLS, registration=FAST, progress=False)
    _, atlas = load_model(out)
    border = np.zeros(SHAPE, bool)
    border[[0, -1]] = True  # first and last z slices: one subject's CT ends before them
    assert np.abs(q[border][:, 2]).min() > 10.0 + SP[0]  # ... and they hold limb only, no bone
    np.testing.assert_allclose(atlas.mean[border], 0.02, atol=1e-4)
    assert atlas.var[border].max() < 1e-8
    inside = np.linalg.norm(q / np.array([20.0, 12.0, 10.0]), axis=-1) < 0.8
    np.testing.assert_allclose(atlas.mean[inside], 0.05, atol=1e-3)


def test_build_is_cached_and_resumes_after_an_interruption(tmp_path):
    template, subjects = _template(), _population(4, seed=3)
    out = tmp_path / "m.npz"

    class Stop(Exception):
        pass

    def stop_after_two(i, sid):
        if i == 1:
            raise Stop()

    log = []
    with pytest.raises(Stop):
        build_model(template, _counting(subjects, log), out, max_cells=MAX_CELLS, registration=FAST,
                    progress=False, on_subject=stop_after_two)
    assert log == ["p0", "p1"] and not out.exists()
    assert len(os.listdir(str(out) + ".cache")) == 2
    log.clear()
    build_model(template, _counting(subjects, log), out, max_cells=MAX_CELLS, registration=FAST, progress=False)
    assert log == ["p2", "p3"]  # the first two came from the cache
    assert not os.path.exists(str(out) + ".cache")  # removed after success
    resumed, _ = load_model(out)
    fresh = tmp_path / "fresh.npz"
    build_model(template, subjects, fresh, max_cells=MAX_CELLS, registration=FAST, progress=False)
    ref, _ = load_model(fresh)
    torch.testing.assert_close(resumed.mean, ref.mean, rtol=0, atol=0)  # same bits
    torch.testing.assert_close(resumed.sigma, ref.sigma, rtol=0, atol=0)
    # up to date: nothing is loaded again; other settings: rebuilt
    log.clear()
    build_model(template, _counting(subjects, log), out, max_cells=MAX_CELLS, registration=FAST, progress=False)
    assert log == []
    build_model(template, _counting(subjects, log), out, n_modes=1, max_cells=MAX_CELLS, registration=FAST,
                progress=False)
    assert len(log) == 4 and load_model(out)[0].n_modes == 1


def test_build_rejects_bad_populations(tmp_path):
    template = _template()
    s = _ellipsoid((20, 12, 10))
    with pytest.raises(ValueError, match="at least 2"):
        build_model(template, [s], tmp_path / "x.npz", progress=False)
    with pytest.raises(ValueError, match="unique"):
        build_model(template, [s, s], tmp_path / "x.npz", progress=False)
    with pytest.raises(TypeError, match="Subject"):
        build_model(template, ["a", "b"], tmp_path / "x.npz", progress=False)
