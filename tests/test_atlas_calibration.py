"""The density atlas scaled to the scan (clgs.shape.calibration): the least-squares factors against
known answers, their limits and errors, and a whole run's start on the ellipsoid of
test_shape_guided scanned with its bone denser and its tissue lighter than its atlas says."""
import numpy as np
import pytest
import test_shape_guided as ellipsoid
import torch
from test_shape_guided import _small, geometry

from clgs.anatomy import AnatomyParts
from clgs.errors import InputError
from clgs.shape import calibration as C

template, shape_model, tissue_atlas = ellipsoid.template, ellipsoid.shape_model, ellipsoid.tissue_atlas


def _parts(seed=0):
    rng = np.random.default_rng(seed)
    bone = np.zeros((3, 20, 30))
    bone[:, 5:12, 10:18] = rng.uniform(1, 2, (3, 7, 8))
    rest = rng.uniform(0.2, 1.0, (3, 20, 30))
    return bone, rest


def test_the_factors_are_the_least_squares_answer():
    bone, rest = _parts()
    b, t = C.fit_factors(bone, rest, 1.3 * bone + 0.8 * rest)
    assert (b, t) == pytest.approx((1.3, 0.8), abs=1e-9)
    noise = np.random.default_rng(1).normal(0, 0.01, bone.shape)
    b, t = C.fit_factors(bone, rest, 1.3 * bone + 0.8 * rest + noise)
    A = np.stack([bone.ravel(), rest.ravel()], 1)
    ref = np.linalg.lstsq(A, (1.3 * bone + 0.8 * rest + noise).ravel(), rcond=None)[0]
    assert (b, t) == pytest.approx(tuple(ref), abs=1e-9)


def test_the_factors_are_clipped_and_a_lone_or_parallel_rest_gives_one():
    bone, rest = _parts()
    lo, hi = C.FACTOR_RANGE
    assert C.fit_factors(bone, rest, 5.0 * bone + 0.1 * rest) == (hi, lo)
    assert C.fit_factors(bone, None, 1.5 * bone) == pytest.approx((1.5, None))
    assert C.fit_factors(bone, np.zeros_like(rest), 1.5 * bone)[1] is None
    b, t = C.fit_factors(bone, 2.0 * bone, 3.0 * bone)  # no way to tell them apart: one factor
    assert t is None and b == pytest.approx(2.0)


def test_no_bone_in_the_views_or_a_non_finite_view_is_a_clear_error():
    bone, rest = _parts()
    with pytest.raises(InputError, match="atlas_calibration=off"):
        C.fit_factors(np.zeros_like(bone), rest, rest)
    bad = bone.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises((InputError, FloatingPointError)):
        C.fit_factors(bone, rest, bad)


def test_scaling_a_sets_densities_keeps_its_gradient():
    from clgs.fit.gaussians import GaussianSet

    rng = np.random.default_rng(0)
    n = 50
    g = GaussianSet(rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32), np.full((n, 3), 0.05, np.float32),
                    np.tile(np.float32([1, 0, 0, 0]), (n, 1)), rng.uniform(1e-3, 3.0, n).astype(np.float32),
                    box=(1.0, 1.0, 1.0))
    before = g.tensors()[3].detach().clone()
    C.scale_densities(g, 1.7)
    after = g.tensors()[3]
    assert after.requires_grad
    np.testing.assert_allclose(after.detach().numpy(), 1.7 * before.numpy(), rtol=1e-5)


def _scan(template, atlas, bone=0.05, tissue=0.01, n_views=4):
    """The ellipsoid (``bone`` per mm) in the tissue ``atlas`` holds around it (``tissue`` per
    mm), which the atlas holds at 0.05 and 0.01. (Tissue beyond the atlas's grid would count in
    the tissue's factor: the module's doc.)"""
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector

    geo = geometry(n_views, 48)
    pts = geo.volume_grid(scene=False).points()
    d = template.sdf_at(pts)
    around = atlas.mean_at(pts.reshape(-1, 3)).reshape(d.shape) > 0.005
    vol = np.where(d < 0, bone, np.where(around, tissue, 0.0)).astype(np.float32)
    return Scan(geo, np.asarray(CTProjector(geo).forward(vol), np.float32), truth=vol)


def _run(scan, template, shape_model, tissue_atlas, **kw):
    from clgs.methods.shape_guided import reconstruct_shape_guided

    return reconstruct_shape_guided(scan, AnatomyParts(template, shape_model, tissue_atlas), iterations=1,
                                    **_small(**kw))


def test_a_scan_denser_in_bone_and_lighter_around_it_is_found_so_and_its_truth_is_never_read(template, shape_model,
                                                                                            tissue_atlas):
    """The same ellipsoid scanned with the atlas's densities and with its bone 1.3 times denser and
    its tissue 0.8 times: the factors' ratio is the change (on the atlas's own densities they are
    within a few % of 1: the atlas's 2 mm bone read on another 2 mm grid)."""
    parts = (template, shape_model, tissue_atlas)
    own = _run(_scan(template, tissue_atlas), *parts, atlas_calibration="fit", fit_size="off").trainer.config
    assert own["atlas_bone_factor"] == pytest.approx(1.0, abs=0.05)
    assert own["atlas_rest_factor"] == pytest.approx(1.0, abs=0.05)
    shifted = _scan(template, tissue_atlas, bone=0.065, tissue=0.008)
    cfg = _run(shifted, *parts, atlas_calibration="fit", fit_size="off").trainer.config
    assert cfg["atlas_bone_factor"] / own["atlas_bone_factor"] == pytest.approx(1.3, abs=0.02)
    assert cfg["atlas_rest_factor"] / own["atlas_rest_factor"] == pytest.approx(0.8, abs=0.04)
    shifted.truth = None
    blind = _run(shifted, *parts, atlas_calibration="fit", fit_size="off").trainer.config
    assert (blind["atlas_bone_factor"], blind["atlas_rest_factor"]) == (cfg["atlas_bone_factor"],
                                                                        cfg["atlas_rest_factor"])


def test_the_start_and_the_prior_take_the_factors(template, shape_model, tissue_atlas):
    """The start's densities and the prior's atlas scaled by the factors (given here: the same
    path a fitted pair takes); off, the run is the one before calibration existed."""
    scan = _scan(template, tissue_atlas)
    plain = _run(scan, template, shape_model, tissue_atlas, fit_size="off")
    scaled = _run(scan, template, shape_model, tissue_atlas, fit_size="off", atlas_bone_factor=1.5,
                  atlas_rest_factor=0.5)
    assert plain.trainer.config["atlas_bone_factor"] is None
    (shape0, free0), (shape1, free1) = (r.trainer.sets for r in (plain, scaled))
    with torch.no_grad():
        # one iteration of Adam has moved each density by at most its learning rate's step
        d0, d1 = shape0.tensors()[3], shape1.tensors()[3]
        assert float(torch.median(d1 / d0)) == pytest.approx(1.5, rel=0.05)
        f0, f1 = free0.tensors()[3], free1.tensors()[3]
        assert float(torch.median(f1 / f0)) == pytest.approx(0.5, rel=0.05)
    prior = next(t.fn for t in scaled.trainer.losses if t.name == "density")
    assert prior.factors == (1.5, 0.5)
    bone, rest = prior.atlas_parts(shape1, scan.geometry.volume_grid(scene=True))
    inside = template.sdf_at(scan.geometry.volume_grid(scene=False).points()) < -3.0
    np.testing.assert_allclose(bone[inside], 0.05, atol=1e-6)
    assert float(np.abs(rest[inside]).max()) < 1e-6


def test_a_calibrated_run_resumes_with_its_factors_bit_for_bit(template, shape_model, tissue_atlas, tmp_path):
    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _scan(template, tissue_atlas, bone=0.065, tissue=0.008)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    kw = _small(atlas_calibration="fit", fit_size="off")
    kw.pop("checkpoint_every")
    full = reconstruct_shape_guided(scan, parts, tmp_path / "a", iterations=12, checkpoint_every=6, **kw)
    reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=6, checkpoint_every=6, schedule_iterations=12,
                             **kw)
    resumed = reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=12, resume=True, progress=False)
    assert resumed.trainer.config["atlas_bone_factor"] == full.trainer.config["atlas_bone_factor"]
    np.testing.assert_array_equal(full.volume, resumed.volume)


def test_experiment_records_made_before_the_calibration_count_as_off(tmp_path):
    """A scaled atlas changes every shape-guided figure: a resumed experiment must not keep a
    record made without it beside a run with it (nor the reverse); R2-Gaussian mode has no atlas."""
    from clgs.experiment import _check_same_run, _made_with

    old = {"iterations": 1000, "seed": 0, "settings": {},
               "limb_outline": "auto", "fit_size": "on", "fit_length": "auto", "schedule": "fast",
           "lambda_shape": 0.0}
    ap_lat = np.radians([0.0, 90.0])
    fit = _made_with("shape", 1000, 0, {"shape": {"atlas_calibration": "fit"}}, "same", ap_lat)
    off = _made_with("shape", 1000, 0, {"shape": {"atlas_calibration": "off"}}, "same", ap_lat)
    assert (fit["atlas_calibration"], off["atlas_calibration"]) == ("fit", "off")
    assert fit["settings"] == off["settings"] == {}
    with pytest.raises(InputError, match="atlas_calibration 'off', this run asks for 'fit'"):
        _check_same_run(tmp_path / "run.json", old, fit)
    _check_same_run(tmp_path / "run.json", old, off)
    with pytest.raises(InputError, match="atlas_calibration 'fit', this run asks for 'off'"):
        _check_same_run(tmp_path / "run.json", {**old, "atlas_calibration": "fit"}, off)
    assert "atlas_calibration" not in _made_with("r2gs", 1000, 0, {}, "same")


def test_a_scan_in_other_units_is_clipped_and_said_so(template, shape_model, tissue_atlas):
    """Projections ten times too large (attenuation per cm given as per mm): the factors stop at
    the range's end and a warning names the likely cause."""
    scan = _scan(template, tissue_atlas)
    scan.projections = scan.projections * 10.0
    scan.truth = scan.truth * 10.0
    with pytest.warns(UserWarning, match="per mm"):
        cfg = _run(scan, template, shape_model, tissue_atlas, atlas_calibration="fit", fit_size="off").trainer.config
    assert cfg["atlas_bone_factor"] == C.FACTOR_RANGE[1]
