"""A bone beyond the shape model's sizes: the size search, the fitted size in the shape-guided set
(centres, their gradient, the inverse map, checkpoints) and in a whole run. The ellipsoid template
of test_shape_guided in its soft tissue, scanned at 0.8, 1.0 and 1.25 times its size."""
import json

import numpy as np
import pytest
import test_shape_guided as ellipsoid
import torch
from test_shape_guided import _small, geometry

from clgs.anatomy import AnatomyParts

# the ellipsoid's fixtures, shared with test_shape_guided
template, shape_model, tissue_atlas = ellipsoid.template, ellipsoid.shape_model, ellipsoid.tissue_atlas


def _scan_at(template, size, n_views=8):
    """The ellipsoid scaled by ``size`` about its centroid, in 0.01/mm tissue within 28 mm of z."""
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector
    from clgs.shape.size import size_centre

    geo = geometry(n_views, 48)
    pts = geo.volume_grid(scene=False).points()
    c = size_centre(template)
    d = template.sdf_at(c + (pts - c) / size)
    r = np.linalg.norm(pts[..., :2], axis=-1)
    truth = np.where(d < 0, 0.05, np.where(r < 28.0, 0.01, 0.0)).astype(np.float32)
    return Scan(geo, np.asarray(CTProjector(geo).forward(truth), np.float32), truth=truth)


def _starts(template, atlas, geo):
    from clgs.shape.initialise import initialise, initialise_surroundings

    init = initialise(template, atlas, geo, 1500, seed=0)
    return init, initialise_surroundings(init, template, atlas, geo, 500, threshold=0.005, seed=1)


@pytest.mark.parametrize("size", [0.8, 1.0, 1.25])
def test_the_search_finds_the_bones_size_from_its_projections(template, tissue_atlas, size):
    from clgs.fit.trainer import Backend
    from clgs.shape.size import SIZES, search_size, size_centre

    scan = _scan_at(template, size)
    bone, tissue = _starts(template, tissue_atlas, scan.geometry)
    best, losses = search_size(scan, Backend("cl"), 1.0, bone, tissue, size_centre(template))
    assert abs(best - size) <= 0.03
    assert losses.shape == SIZES.shape and np.all(np.isfinite(losses))
    assert losses.min() < 0.7 * losses[np.argmin(np.abs(SIZES - 1.4))]  # a clear minimum, not a flat curve


def test_tissue_is_stretched_along_the_leg_for_a_larger_bone_only():
    from clgs.shape.size import stretched_surroundings

    pts = np.array([[10.0, -5.0, 40.0], [0.0, 3.0, -20.0]])
    c = np.array([1.0, 2.0, 10.0])
    np.testing.assert_array_equal(stretched_surroundings(pts, c, 0.8), pts)
    out = stretched_surroundings(pts, c, 1.5)
    np.testing.assert_array_equal(out[:, :2], pts[:, :2])
    np.testing.assert_allclose(out[:, 2], [55.0, -35.0])


def _set(template, shape_model, size=1.3, alpha=(0.4, -0.3)):
    from clgs.fit.gaussians import Schedule
    from clgs.shape.gaussian_set import ShapeGuidedSet
    from clgs.shape.initialise import sample_reference_centres
    from clgs.shape.size import size_centre

    geo = geometry()
    p = sample_reference_centres(template, 200, seed=0)
    n = len(p)
    sched = {k: Schedule(0.01) for k in ("alpha", "log_size", "scales", "quats", "densities")}
    return ShapeGuidedSet(p, np.full((n, 3), 0.02, np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          np.full(n, 0.1, np.float32), shape_model=shape_model, geometry=geo,
                          box=(-1.0, 1.0), scale_bounds=(1e-4, 1.0), schedules=sched, alpha=alpha, size=size,
                          size_centre_mm=size_centre(template))


def test_a_sized_set_scales_its_centres_about_the_centre_and_its_map_inverts_it(template, shape_model):
    from clgs.shape.gaussian_set import ShapeGuidedSet

    sized, plain = _set(template, shape_model, 1.3), _set(template, shape_model, None)
    assert sized.fits_size and not plain.fits_size and plain.size == 1.0
    assert sized.size == pytest.approx(1.3, rel=1e-6)
    c = sized.size_centre
    with torch.no_grad():
        np.testing.assert_allclose(sized.centres_mm(), c + 1.3 * (plain.centres_mm() - c), atol=1e-4)
        # the inverse map takes the sized subject's points back to the template's
        back = sized.to_template(sized.centres_mm())
    np.testing.assert_allclose(back, sized.p_ref, atol=0.05)  # two fixed-point steps: ~0.01 mm here
    with pytest.raises(ValueError, match="positive"):
        _set(template, shape_model, -1.0)
    assert isinstance(sized, ShapeGuidedSet)


def test_the_centres_gradient_wrt_the_size_is_the_derivative_of_the_map(template, shape_model):
    """d centres / d log s = s (x - c): autograd against that and against a central difference."""
    s = _set(template, shape_model, 1.3)
    g = torch.randn(len(s), 3, generator=torch.Generator().manual_seed(0))
    (s.centres_mm() * g).sum().backward()
    got = float(s.params["log_size"].grad[0])
    with torch.no_grad():
        x = s.centres_mm()
        analytic = float(((x - s.size_centre) * g).sum())
        h = 1e-3
        s.params["log_size"] += h
        up = float((s.centres_mm() * g).sum())
        s.params["log_size"] -= 2 * h
        down = float((s.centres_mm() * g).sum())
    assert got == pytest.approx(analytic, rel=1e-5)
    assert got == pytest.approx((up - down) / (2 * h), rel=2e-3)


def test_a_larger_bone_is_fitted_at_its_size_and_beats_the_models_own(template, shape_model, tissue_atlas,
                                                                        tmp_path):
    """1.25 x the template: the size is fitted (the default), the model surface and the volume gain. (The test
    model's first mode stretches z, which trades a little with the size: measured 1.195 with alpha_1
    0.02 after 150 iterations; the model surface 0.85 mm against 2.44 mm without a size, 3D PSNR
    22.29 against 21.41 dB.)"""
    from clgs.methods.shape_guided import deformed_template_surface, reconstruct_shape_guided
    from clgs.metrics import psnr3d
    from clgs.shape.size import size_centre

    scan = _scan_at(template, 1.25)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    kw = _small(alpha_freeze=5, alpha_init_iterations=40)
    sized = reconstruct_shape_guided(scan, parts, tmp_path / "a", iterations=150, **kw)
    off = reconstruct_shape_guided(scan, parts, None, iterations=150, fit_size="off", **kw)
    s = sized.trainer.sets[0]
    assert s.fits_size and not off.trainer.sets[0].fits_size
    auto = reconstruct_shape_guided(scan, parts, None, iterations=1, fit_size="auto", **kw)
    assert auto.trainer.sets[0].fits_size  # beyond the model's sizes: auto fits one too
    assert s.size == pytest.approx(1.25, abs=0.08)
    assert json.loads((tmp_path / "a" / "alpha.json").read_text())["size"] == pytest.approx(s.size)
    assert psnr3d(sized.volume, scan.truth) > psnr3d(off.volume, scan.truth) + 0.5
    c = size_centre(template)
    truth_v = c + 1.25 * (template.vertices - c)

    def mean_distance(res):
        v, _ = deformed_template_surface(template, res.trainer.sets[0])
        from scipy.spatial import cKDTree

        return float(cKDTree(truth_v).query(v)[0].mean())

    assert mean_distance(sized) < 1.2 and mean_distance(off) > 2.0


def test_auto_leaves_a_bone_of_the_models_size_as_it_was(template, shape_model, tissue_atlas):
    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _scan_at(template, 1.0)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    auto = reconstruct_shape_guided(scan, parts, None, iterations=20, fit_size="auto", **_small(alpha_freeze=5))
    off = reconstruct_shape_guided(scan, parts, None, iterations=20, fit_size="off", **_small(alpha_freeze=5))
    assert not auto.trainer.sets[0].fits_size
    np.testing.assert_array_equal(auto.volume, off.volume)


def test_a_sized_run_resumes_bit_for_bit_and_refuses_a_checkpoint_without_one(template, shape_model, tissue_atlas,
                                                                              tmp_path):
    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _scan_at(template, 1.25)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    kw = _small(alpha_freeze=3)
    kw.pop("checkpoint_every")
    full = reconstruct_shape_guided(scan, parts, tmp_path / "a", iterations=30, checkpoint_every=15, **kw)
    reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=15, checkpoint_every=15,
                             schedule_iterations=30, **kw)
    resumed = reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=30, resume=True, progress=False)
    assert resumed.trainer.sets[0].fits_size
    np.testing.assert_array_equal(full.volume, resumed.volume)
    assert full.trainer.sets[0].size == resumed.trainer.sets[0].size
    # a checkpoint with a size loaded into a set without one (and the reverse) is refused
    state = full.trainer.sets[0].state_dict()
    plain = _set(template, shape_model, None)
    with pytest.raises(ValueError, match="with a fitted size"):
        plain.load_state_dict({**state, "p_ref": plain.p_ref})


@pytest.mark.parametrize("size", [0.8, 1.3])
def test_the_density_prior_scales_the_bone_and_only_a_larger_bones_tissue(template, shape_model, tissue_atlas,
                                                                          size):
    """Along the x axis through the centre: inside the scaled bone the atlas is read with the size
    undone; in the tissue beyond, a smaller bone's tissue is read where it is (a larger one's with
    the size undone); a smaller bone's ring (outside it, inside the template's bone) is not held."""
    from clgs.shape.priors import DensityPrior

    s = _set(template, shape_model, size, alpha=(0.0, 0.0))
    prior = DensityPrior(tissue_atlas, template, geometry(), 1.0, 0.05, 8, field="all")
    c = s.size_centre
    x = torch.linspace(0.0, 26.0, 53)  # every 0.5 mm; the ellipsoid's x semi-axis: 14 mm
    pts = c + torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], 1)
    with torch.no_grad():
        x_bone = s.to_template(pts)
        mean, var, at, keep = prior._sized_atlas(s, pts, x_bone)
    inside = x < 14.0 * size - 3.0  # two voxels of the atlas (2 mm) clear of its edge
    np.testing.assert_allclose(at[inside], x_bone[inside], atol=1e-5)
    np.testing.assert_allclose(mean[inside], 0.05, atol=1e-6)
    far = (x > 15.0 * max(size, 1.0)) & (x / max(size, 1.0) < 20.5)  # within the atlas (to 22 mm)
    tissue_at = c + (pts - c) / max(size, 1.0)
    np.testing.assert_allclose(at[far], tissue_at[far], atol=1e-3)
    np.testing.assert_allclose(mean[far], 0.01, atol=1e-6)
    ring = (x > 14.0 * size + 1.0) & (x < 12.9)
    assert bool(ring.any()) == (size < 1)
    assert torch.all(keep[ring] == 0) and torch.all(keep[~ring & (inside | far)] == 1)


def test_the_method_entry_reports_the_fitted_size(template, shape_model, tissue_atlas, tmp_path, capsys):
    """What `clgs reconstruct --method shape --fit-size on` runs: the size in the report and on stderr."""
    from clgs.methods.shape_guided import run_method

    scan = _scan_at(template, 1.25)
    kw = _small(alpha_freeze=3)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    out = run_method(scan, tmp_path / "r", 10, anatomy=parts, fit_size="on", **kw)
    assert out["info"]["size"] == pytest.approx(1.25, abs=0.08)
    assert "bone size: 1.2" in capsys.readouterr().err
    off = run_method(scan, tmp_path / "o", 10, anatomy=parts, fit_size="off", **kw)
    assert off["info"]["size"] is None


def test_experiment_records_made_before_the_size_count_as_made_without_one(tmp_path):
    """A resumed experiment must not mix runs with and without a fitted size in one table."""
    from clgs.errors import InputError
    from clgs.experiment import _check_same_run, _made_with

    # the record below is from before schedules and the shape prior's weight were named too: it ran
    # the paper's
    paper = {"schedule": "paper", "lambda_shape": 1e-4, "limb_outline": "off"}
    want = _made_with("shape", 1000, 0, {"shape": paper}, "same")
    assert want["fit_size"] == "on" and want["settings"] == {} and want["schedule"] == "paper"
    assert want["lambda_shape"] == 1e-4
    old = {"iterations": 1000, "seed": 0, "settings": {}}  # a record from before the size
    with pytest.raises(InputError, match="fit_size 'off'"):
        _check_same_run(tmp_path / "run.json", old, want)
    _check_same_run(tmp_path / "run.json", old,
                    _made_with("shape", 1000, 0, {"shape": {"fit_size": "off", **paper}}, "same"))
    # nor runs of two schedules: records from before schedules count as the paper's
    assert _made_with("shape", 1000, 0, {}, "same")["schedule"] == "fast"
    with pytest.raises(InputError, match="schedule 'paper', this run asks for 'fast'"):
        _check_same_run(tmp_path / "run.json", {**old, "fit_size": "off"},
                        _made_with("shape", 1000, 0, {"shape": {"fit_size": "off", "lambda_shape": 1e-4}}, "same"))
    assert "fit_size" not in _made_with("r2gs", 1000, 0, {}, "same")
    assert "fit_size" not in _made_with("init", 1000, 0, {}, "same")  # no shape model bound: no size


def test_experiment_records_made_before_the_shape_prior_weight_was_named_count_as_the_papers(tmp_path):
    """The default shape prior weight changed from the paper's 1e-4 to 0: a resumed experiment must
    not keep an older record beside a new run."""
    from clgs.errors import InputError
    from clgs.experiment import _check_same_run, _made_with

    old = {"iterations": 1000, "seed": 0, "settings": {},
               "limb_outline": "auto", "fit_size": "on", "fit_length": "auto", "schedule": "fast"}
    want = _made_with("shape", 1000, 0, {}, "same")
    assert want["lambda_shape"] == 0.0 and want["settings"] == {}
    with pytest.raises(InputError, match="lambda_shape 0.0001, this run asks for 0.0"):
        _check_same_run(tmp_path / "run.json", old, want)
    _check_same_run(tmp_path / "run.json", old, _made_with("shape", 1000, 0, {"shape": {"lambda_shape": 1e-4}}, "same"))
    assert "lambda_shape" not in _made_with("r2gs", 1000, 0, {}, "same")


def test_experiment_records_made_before_the_registrations_tissue_was_named_count_as_held_on_the_free_set(tmp_path):
    """The tissue the registration holds (register_tissue) changes the fitted shape: a resumed
    experiment must not keep an older record (which held the free set's start) beside a run that
    held the FDK's tissue."""
    from clgs.errors import InputError
    from clgs.experiment import _check_same_run, _made_with

    old = {"iterations": 1000, "seed": 0, "settings": {},
               "limb_outline": "auto", "fit_size": "on", "fit_length": "auto", "schedule": "fast",
           "lambda_shape": 0.0}
    want = _made_with("shape", 1000, 0, {"shape": {"register_tissue": "fdk"}}, "same")
    assert want["register_tissue"] == "fdk" and want["settings"] == {}
    with pytest.raises(InputError, match="register_tissue 'free', this run asks for 'fdk'"):
        _check_same_run(tmp_path / "run.json", old, want)
    _check_same_run(tmp_path / "run.json", old, _made_with("shape", 1000, 0, {"shape": {"register_tissue": "free"}},
                                                           "same"))
    assert "register_tissue" not in _made_with("r2gs", 1000, 0, {}, "same")
    # the default, auto, is recorded as what it chose for the views: AP + lateral kept the free
    # set's start (an older record stays good), 5 views over a half-turn the FDK's
    ap_lat = np.radians([0.0, 90.0])
    assert _made_with("shape", 1000, 0, {}, "same", ap_lat)["register_tissue"] == "free"
    _check_same_run(tmp_path / "run.json", old, _made_with("shape", 1000, 0, {}, "same", ap_lat))
    five = np.linspace(0, np.pi, 5, endpoint=False)
    with pytest.raises(InputError, match="register_tissue 'free', this run asks for 'fdk'"):  # the residual held apart
        _check_same_run(tmp_path / "run.json", old,
                        _made_with("shape", 1000, 0, {"shape": {"residual": "off"}}, "same", five))
    with pytest.raises(InputError, match="residual 'off', this run asks for 'on'"):  # the default there fits it
        _check_same_run(tmp_path / "run.json", old, _made_with("shape", 1000, 0, {}, "same", five))


def test_experiment_records_name_the_fdk_registrations_passes_only_where_they_run(tmp_path):
    """The FDK's tissue's registrations in a row (register_passes) change the fitted shape: a
    5-view record made with one pass (every record before they were named) is refused beside a
    run of three (the default), and so is one of three passes made before a later pass's hole had
    its margin; where the free set's start is held the passes do not run and are not recorded."""
    from clgs.errors import InputError
    from clgs.experiment import _check_same_run, _made_with

    five = np.linspace(0, np.pi, 5, endpoint=False)
    # the residual as a 5-view run records it today (it has its own check)
    one_pass = {"iterations": 1000, "seed": 0, "settings": {},
               "limb_outline": "auto", "fit_size": "on", "fit_length": "auto",
                "schedule": "fast", "lambda_shape": 0.0, "register_tissue": "fdk", "residual": "on"}
    want = _made_with("shape", 1000, 0, {"shape": {"register_passes": 3}}, "same", five)
    assert want["register_passes"] == 3 and want["settings"] == {} and want["pass_hole_margin_mm"] == 3.0
    assert _made_with("shape", 1000, 0, {}, "same", five) == want  # three: the default
    with pytest.raises(InputError, match="register_passes 1, this run asks for 3"):
        _check_same_run(tmp_path / "run.json", one_pass, want)
    with pytest.raises(InputError, match="pass_hole_margin_mm 0.0, this run asks for 3.0"):
        _check_same_run(tmp_path / "run.json", {**one_pass, "register_passes": 3}, want)
    _check_same_run(tmp_path / "run.json", {**one_pass, "register_passes": 3, "pass_hole_margin_mm": 3.0}, want)
    no_margin = _made_with("shape", 1000, 0, {"shape": {"pass_hole_margin_mm": 0}}, "same", five)
    assert no_margin["pass_hole_margin_mm"] == 0.0 and no_margin["settings"] == {}
    _check_same_run(tmp_path / "run.json", {**one_pass, "register_passes": 3}, no_margin)  # as made before it
    one = _made_with("shape", 1000, 0, {"shape": {"register_passes": 1}}, "same", five)
    assert "register_passes" not in one and "pass_hole_margin_mm" not in one
    assert _made_with("shape", 1000, 0, {"shape": {"register_passes": 1, "pass_hole_margin_mm": 5}}, "same",
                      five)["settings"] == {}  # no later pass: the margin changes nothing
    _check_same_run(tmp_path / "run.json", one_pass, one)
    ap_lat = _made_with("shape", 1000, 0, {"shape": {"register_passes": 2}}, "same", np.radians([0.0, 90.0]))
    assert "register_passes" not in ap_lat and ap_lat["settings"] == {}


def test_the_experiment_table_names_each_subjects_fitted_sizes():
    from clgs.experiment import markdown_tables, summarise

    rows = [{"subject": sid, "views": v, "method": "shape", "psnr3d": 30.0, "ssim3d": 0.9, "seconds": 1.0,
             "model_size": size} for sid, v, size in (("20", 5, 1.047), ("20", 10, 1.052), ("21", 5, 0.99))]
    rows.append({"subject": "22", "views": 5, "method": "shape", "psnr3d": 30.0, "ssim3d": 0.9, "seconds": 1.0,
                 "model_size": None})  # made with --fit-size off
    text = markdown_tables(rows, summarise(rows, [5, 10], None), [5, 10], None)
    line = next(x for x in text.splitlines() if x.startswith("Fitted bone size"))
    assert line.endswith(": 20 1.047-1.052, 21 0.990")
