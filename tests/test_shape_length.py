"""A bone longer or shorter for its girth than the model's: the length factor along the leg
(``fit_length``), searched with the size and held through the fit. The ellipsoid template of
test_shape_guided, its soft tissue along z, scanned stretched along z."""
import json

import numpy as np
import pytest
import test_shape_guided as ellipsoid
import torch
from test_shape_guided import _small, geometry
from test_shape_size import _set, _starts

from clgs.anatomy import AnatomyParts
from clgs.errors import InputError

template, shape_model, tissue_atlas = ellipsoid.template, ellipsoid.shape_model, ellipsoid.tissue_atlas


def _scan_stretched(template, size, length, n_views=8, tissue: float = 0.01):
    """The ellipsoid scaled by ``size`` about its centroid and by ``length`` more along z, in
    ``tissue`` /mm within 28 mm of the z axis."""
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector
    from clgs.shape.size import size_centre

    geo = geometry(n_views, 48)
    pts = geo.volume_grid(scene=False).points()
    c = size_centre(template)
    d = template.sdf_at(c + (pts - c) / (size * np.array([1.0, 1.0, length])))
    r = np.linalg.norm(pts[..., :2], axis=-1)
    truth = np.where(d < 0, 0.05, np.where(r < 28.0, tissue, 0.0)).astype(np.float32)
    return Scan(geo, np.asarray(CTProjector(geo).forward(truth), np.float32), truth=truth)


@pytest.mark.parametrize("length", [1.0, 1.12, 0.9])
def test_the_search_tells_a_longer_or_shorter_bone_from_a_larger_or_smaller_one(template, tissue_atlas, length):
    """The bone alone (no tissue in the scan or the search), at 0.8 of the template's size so that
    the longer one still ends inside the 48 mm grid: one of the model's shape keeps a length of 1
    and its size; one 1.12 times longer (0.9 times shorter) for its girth is found so, where the
    size alone takes it for a larger (smaller) bone; with the gain asked of ``fit_length="auto"``
    the length is kept only where it lowers the L1 by more than that share."""
    from clgs.fit.trainer import Backend
    from clgs.shape.size import LENGTH_GAIN, search_size_and_length, size_centre

    scan = _scan_stretched(template, 0.8, length, tissue=0.0)
    bone, _ = _starts(template, tissue_atlas, scan.geometry)
    size, k, alone, share = search_size_and_length(scan, Backend("cl"), 1.0, bone, None, size_centre(template),
                                                   gain=LENGTH_GAIN)
    assert size == pytest.approx(0.8, abs=0.03)
    if length == 1.0:
        assert (k, alone) == (1.0, size) and share <= LENGTH_GAIN
    else:
        assert k == pytest.approx(length, abs=0.015) and share > 0.1
        assert (alone - size) * (length - 1.0) > 0.001  # the size alone took the length for a size


def test_a_stretched_bone_carries_each_gaussians_covariance():
    """``stretched_bone``: centres by c + A (x - c), covariances A S A for A = diag(s, s, s k),
    against the reference's rotation of the quaternions; with k = 1 the plain scaling to the bit."""
    from clgs.reference.gaussians import quaternion_to_rotation
    from clgs.shape.size import stretched_bone

    rng = np.random.default_rng(3)
    q = rng.normal(size=(40, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[0] = (1.0, 0.0, 0.0, 0.0)
    sc, x, c = rng.uniform(0.3, 3.0, (40, 3)), rng.normal(size=(40, 3)) * 20, np.array([1.0, -2.0, 5.0])

    def cov(q, sc):
        r = quaternion_to_rotation(torch.as_tensor(q, dtype=torch.float64)).numpy()
        return r @ (sc[:, :, None] ** 2 * np.swapaxes(r, 1, 2))

    a = np.diag([1.1, 1.1, 1.1 * 1.2])
    x2, sc2, q2 = stretched_bone(x, sc, q, c, 1.1, 1.2)
    np.testing.assert_allclose(x2, c + (x - c) @ a, rtol=1e-12)
    np.testing.assert_allclose(cov(q2, sc2), a @ cov(q, sc) @ a, atol=1e-10)
    np.testing.assert_allclose(np.linalg.norm(q2, axis=1), 1.0, rtol=1e-12)
    x1, sc1, q1 = stretched_bone(x, sc, q, c, 1.1)
    np.testing.assert_array_equal(x1, c + 1.1 * (x - c))
    np.testing.assert_array_equal(sc1, sc * 1.1)
    assert q1 is q or np.array_equal(q1, q)


def test_the_tissue_runs_the_length_of_its_bone():
    from clgs.shape.size import stretched_surroundings

    pts = np.array([[10.0, -5.0, 40.0], [0.0, 3.0, -20.0]])
    c = np.array([1.0, 2.0, 10.0])
    out = stretched_surroundings(pts, c, 0.8, 1.5)  # a smaller bone, longer for its girth: its length
    np.testing.assert_array_equal(out[:, :2], pts[:, :2])
    np.testing.assert_allclose(out[:, 2], [55.0, -35.0])
    np.testing.assert_array_equal(stretched_surroundings(pts, c, 0.8, 0.9), pts)  # never compressed
    np.testing.assert_array_equal(stretched_surroundings(pts, c, 1.5), stretched_surroundings(pts, c, 1.5, 1.0))


def _long_set(template, shape_model, size=1.1, length=1.2):
    s = _set(template, shape_model, 1.1)
    from clgs.fit.gaussians import Schedule
    from clgs.shape.gaussian_set import ShapeGuidedSet

    sched = {k: Schedule(0.01) for k in ("alpha", "log_size", "log_length", "scales", "quats", "densities")}
    p = s.p_ref.numpy()
    n = len(p)
    return ShapeGuidedSet(p, np.full((n, 3), 0.02, np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          np.full(n, 0.1, np.float32), shape_model=shape_model, geometry=geometry(),
                          box=(-1.0, 1.0), scale_bounds=(1e-4, 1.0), schedules=sched, alpha=(0.4, -0.3), size=size,
                          size_centre_mm=s.size_centre.numpy() if size is not None else None, length=length)


def test_a_long_set_stretches_its_centres_along_the_leg_and_its_map_inverts_it(template, shape_model):
    long, plain = _long_set(template, shape_model), _set(template, shape_model, None)
    assert long.fits_length and not plain.fits_length and plain.length == 1.0
    assert long.length == pytest.approx(1.2, rel=1e-6)
    c = long.size_centre
    with torch.no_grad():
        want = c + 1.1 * torch.tensor([1.0, 1.0, 1.2]) * (plain.centres_mm() - c)
        np.testing.assert_allclose(long.centres_mm(), want, atol=1e-4)
        back = long.to_template(long.centres_mm())
    np.testing.assert_allclose(back, long.p_ref, atol=0.05)
    assert long.to_numpy()["length"] == pytest.approx(1.2)
    with pytest.raises(ValueError, match="needs a fitted size"):
        _long_set(template, shape_model, size=None)
    with pytest.raises(ValueError, match="positive"):
        _long_set(template, shape_model, length=0.0)
    # a checkpoint with a length loaded into a set without one is refused
    sized = _set(template, shape_model, 1.1)
    with pytest.raises(ValueError, match="with a fitted length"):
        sized.load_state_dict({**long.state_dict(), "p_ref": sized.p_ref})


def test_the_centres_gradient_wrt_the_length_is_the_derivative_of_the_map(template, shape_model):
    """d centres / d log k = (0, 0, s k (z - c_z)): autograd against that and a central difference."""
    s = _long_set(template, shape_model)
    g = torch.randn(len(s), 3, generator=torch.Generator().manual_seed(0))
    (s.centres_mm() * g).sum().backward()
    got = float(s.params["log_length"].grad[0])
    with torch.no_grad():
        x = s.centres_mm()
        analytic = float(((x - s.size_centre)[:, 2] * g[:, 2]).sum())
        h = 1e-3
        s.params["log_length"] += h
        up = float((s.centres_mm() * g).sum())
        s.params["log_length"] -= 2 * h
        down = float((s.centres_mm() * g).sum())
    assert got == pytest.approx(analytic, rel=1e-5)
    assert got == pytest.approx((up - down) / (2 * h), rel=2e-3)


def test_a_run_finds_a_shorter_bones_length_records_it_and_resumes_bit_for_bit(template, shape_model, tissue_atlas,
                                                                              tmp_path):
    """The ellipsoid 0.9 times as long for its girth in the atlas's tissue: the default
    ``fit_length="auto"`` finds the length, holds it, records it (alpha.json, config.json) and a
    resumed run continues bit for bit."""
    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _scan_stretched(template, 1.0, 0.9)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    kw = _small(alpha_freeze=3)
    kw.pop("checkpoint_every")
    full = reconstruct_shape_guided(scan, parts, tmp_path / "a", iterations=30, checkpoint_every=15, **kw)
    s = full.trainer.sets[0]
    assert s.fits_length and s.length == pytest.approx(0.9, abs=0.015)
    assert json.loads((tmp_path / "a" / "alpha.json").read_text())["length"] == pytest.approx(s.length)
    assert json.loads((tmp_path / "a" / "config.json").read_text())["length_factor"] == pytest.approx(s.length)
    reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=15, checkpoint_every=15,
                             schedule_iterations=30, **kw)
    resumed = reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=30, resume=True, progress=False)
    assert resumed.trainer.sets[0].length == s.length  # held, not trained
    np.testing.assert_array_equal(full.volume, resumed.volume)


def test_a_bone_of_the_models_proportions_gets_no_length_and_the_same_run(template, shape_model, tissue_atlas):
    """At the model's proportions the search's best length lowers the L1 by less than the gain
    asked: ``fit_length="auto"`` fits none, and the run is ``fit_length="off"``'s to the bit."""
    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _scan_stretched(template, 1.0, 1.0)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    kw = _small(alpha_freeze=3)
    auto = reconstruct_shape_guided(scan, parts, None, iterations=8, **kw)
    off = reconstruct_shape_guided(scan, parts, None, iterations=8, fit_length="off", **kw)
    assert not auto.trainer.sets[0].fits_length and auto.trainer.sets[0].fits_size
    np.testing.assert_array_equal(auto.volume, off.volume)


def test_the_method_entry_reports_the_length(template, shape_model, tissue_atlas, tmp_path, capsys):
    """What `clgs reconstruct --method shape` runs on a bone 0.9 times as long: the length in the
    report's info and on stderr (the search's line and the size's)."""
    from clgs.methods.shape_guided import run_method

    scan = _scan_stretched(template, 1.0, 0.9)
    out = run_method(scan, tmp_path / "r", 4, anatomy=AnatomyParts(template, shape_model, tissue_atlas),
                     **_small(alpha_freeze=3))
    assert out["info"]["length"] == pytest.approx(0.9, abs=0.015)
    err = capsys.readouterr().err
    assert "bone length: 0.9" in err and "x that along the leg" in err
    off = run_method(scan, tmp_path / "o", 4, anatomy=AnatomyParts(template, shape_model, tissue_atlas),
                     fit_length="off", **_small(alpha_freeze=3))
    assert "length" not in off["info"]


def test_a_given_length_is_held_and_a_length_needs_a_fitted_size(template, shape_model, tissue_atlas):
    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _scan_stretched(template, 1.0, 1.12)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    kw = _small(alpha_freeze=3)
    given = reconstruct_shape_guided(scan, parts, None, iterations=2, length_factor=1.05, **kw)
    assert given.trainer.sets[0].length == pytest.approx(1.05)
    from clgs.methods.shape_guided import ShapeGuidedConfig

    for bad in (dict(fit_length="on", fit_size="off"), dict(length_factor=1.05, fit_size="auto")):
        with pytest.raises(InputError, match="needs fit_size=on"):
            reconstruct_shape_guided(scan, parts, None, iterations=2, **{**kw, **bad})
        with pytest.raises(InputError, match="needs fit_size=on"):  # the settings alone, before any work
            ShapeGuidedConfig(**bad)
    for bad, words in ((0.0, "length_factor"), (float("nan"), "finite")):
        with pytest.raises(InputError, match=words):
            ShapeGuidedConfig(length_factor=bad)
    # the default "auto" asks nothing of the size: with the paper's --fit-size off the run has no length
    plain = reconstruct_shape_guided(scan, parts, None, iterations=2, **{**kw, "fit_size": "off"})
    assert not plain.trainer.sets[0].fits_length


def test_experiment_records_name_the_length_and_older_ones_count_as_without(tmp_path):
    """A resumed experiment must not keep a record made before the length (one size) beside a run
    that may fit one (``fit_length="auto"``, the default); without a fitted size no length is
    fitted and the record says ``"off"``."""
    from clgs.experiment import _check_same_run, _made_with

    want = _made_with("shape", 1000, 0, {}, "same")
    assert want["fit_length"] == "auto" and want["settings"] == {}
    old = {"iterations": 1000, "seed": 0, "settings": {},
               "limb_outline": "auto", "fit_size": "on", "schedule": "fast", "lambda_shape": 0.0,
           "register_tissue": "free", "residual": "off"}
    with pytest.raises(InputError, match="fit_length 'off', this run asks for 'auto'"):
        _check_same_run(tmp_path / "run.json", old, want)
    _check_same_run(tmp_path / "run.json", old, _made_with("shape", 1000, 0, {"shape": {"fit_length": "off"}}, "same"))
    assert _made_with("shape", 1000, 0, {"shape": {"fit_size": "off"}}, "same")["fit_length"] == "off"
    assert "fit_length" not in _made_with("r2gs", 1000, 0, {}, "same")


@pytest.mark.parametrize("length", [1.0, 1.08])
def test_a_femur_made_longer_for_its_girth_gets_that_length_from_five_views(length, tmp_path):
    """The known answer on the femur itself: held-out subject 22 stretched along the leg (its z, the
    template's) by ``length`` about its middle, brought in as a user's surface (aligned with a
    size of its own, as ``--meshes`` does) in the limb drawn for its name, scanned from 5 views:
    the default search (``fit_length="auto"``) finds most of that length (1.06 of 1.08: the
    tissue stretched with the bone thins, which costs a longer bone more than a larger one;
    docs/methods.md); unstretched, no length (the run is the one-size run)."""
    pytest.importorskip("clgs_femur", reason="install with: pip install -e anatomies/femur")
    import math

    import clgs_femur

    from clgs.anatomy import plugins
    from clgs.anatomy.simulation import simulate_subject
    from clgs.experiment import load_experiment_subject
    from clgs.io.mesh import save_mesh
    from clgs.methods.shape_guided import reconstruct_shape_guided

    anatomy = plugins.get_anatomy("femur")
    v, f = clgs_femur.population_model().mesh("22")
    c = v.mean(0)
    save_mesh(tmp_path / "s.stl", c + (v - c) * np.array([1.0, 1.0, length]), f)
    subject = load_experiment_subject(anatomy, "s", {"s": (str(tmp_path / "s.stl"), "mm")}, 0)
    scan = simulate_subject(anatomy, subject, 5, math.pi, True, 0, protocol="same")
    res = reconstruct_shape_guided(scan, anatomy, None, iterations=1, alpha_init_iterations=0, residual="off",
                                   progress=False)
    s = res.trainer.sets[0]
    if length == 1.0:
        assert not s.fits_length and res.trainer.sets[0].fits_size
    else:
        assert s.fits_length and 1.04 <= s.length <= length + 0.01


def test_the_experiments_table_lists_each_subjects_fitted_length():
    """table.md's line of fitted lengths (and sizes): per subject, the range over its runs; none
    where no run fitted one."""
    from clgs.experiment import _per_subject_range

    rows = [{"subject": "b", "model_size": 1.02, "model_length": None},
            {"subject": "b", "model_size": 1.05, "model_length": 1.06},
            {"subject": "a", "model_size": 0.98}]
    assert _per_subject_range(rows, "model_size") == "a 0.980, b 1.020-1.050"
    assert _per_subject_range(rows, "model_length") == "b 1.060"
    assert _per_subject_range([rows[0], rows[2]], "model_length") == ""
