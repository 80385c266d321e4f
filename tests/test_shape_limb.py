"""The limb's outline measured in the views and the atlas's tissue carried onto it
(``limb_outline``, clgs.shape.limb): known ellipses, cone-beam scans of an elliptic cylinder
projected by the OpenCL projector, and the shape-guided run's start and density prior."""
import numpy as np
import pytest
import test_shape_guided as ellipsoid
from test_shape_guided import _small

from clgs.anatomy import AnatomyParts
from clgs.geometry import Geometry, Grid

template, shape_model = ellipsoid.template, ellipsoid.shape_model

AP_LAT = np.array([0.0, np.pi / 2])
FIVE = np.linspace(0, np.pi, 5, endpoint=False)


def _ellipse_mask(grid, centre, radii, nz):
    x = grid.origin[0] + grid.spacing[0] * np.arange(grid.shape[2])
    y = grid.origin[1] + grid.spacing[1] * np.arange(grid.shape[1])
    r = ((x[None, :] - centre[0]) / radii[0]) ** 2 + ((y[:, None] - centre[1]) / radii[1]) ** 2
    return np.broadcast_to(r <= 1.0, (nz,) + r.shape)


@pytest.mark.parametrize("angles", [AP_LAT, FIVE])
def test_the_ellipse_fit_recovers_a_known_ellipse_from_its_extents(angles):
    """A mask of the ellipse centre (5, -3) mm, radii (20, 12) mm on a 0.25 mm grid: from the
    extents along two (AP + lateral) or five view directions, the centre and radii within 0.15 mm;
    a mask touching the grid's side is not measured; one direction pins nothing."""
    from clgs.shape.limb import fit_ellipses, spread_ok

    grid = Grid((3, 240, 240), (-30.0, -30.0, 0.0), (0.25, 0.25, 4.0))
    dirs = np.stack([-np.sin(angles), np.cos(angles)], 1)
    mask = _ellipse_mask(grid, (5.0, -3.0), (20.0, 12.0), 3)
    e = fit_ellipses(mask, grid, dirs)
    assert e.valid.all()
    np.testing.assert_allclose(e.centre, [[5.0, -3.0]] * 3, atol=0.15)
    np.testing.assert_allclose(e.radii, [[20.0, 12.0]] * 3, atol=0.15)
    np.testing.assert_allclose(e.z, [0.0, 4.0, 8.0])
    wide = _ellipse_mask(grid, (5.0, -3.0), (40.0, 12.0), 3)
    assert not fit_ellipses(wide, grid, dirs).valid.any()
    assert spread_ok(dirs) and not spread_ok(dirs[:1]) and not spread_ok(np.array([[0.0, 1.0], [0.0, -1.0]]))
    assert not fit_ellipses(mask, grid, dirs[:1]).valid.any()


def _cylinder_scan(angles, centre=(6.0, -4.0), radii=(30.0, 20.0), det_u=96, density=0.02):
    """A cone-beam scan (DSO 400, DSD 600) of an elliptic cylinder along z, uniform ``density``
    /mm, voxels 0.5 mm across (2 mm along z), projected by the OpenCL projector."""
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector

    geo = Geometry(DSD=600.0, DSO=400.0, nDetector=(40, det_u), dDetector=(1.6, 1.6), nVoxel=(12, 256, 256),
                   dVoxel=(2.0, 0.5, 0.5), angles=np.asarray(angles, float))
    grid = geo.volume_grid(scene=False)
    truth = np.where(_ellipse_mask(grid, centre, radii, 12), density, 0.0).astype(np.float32)
    return Scan(geo, np.asarray(CTProjector(geo).forward(truth), np.float32), truth=truth)


@pytest.mark.parametrize("angles", [AP_LAT, FIVE])
def test_the_scans_outline_is_the_cylinders_ellipse(angles):
    """The outline measured in the projections (the ellipse tangent to the lines from the source
    through each view's silhouette edges) of an elliptic cylinder centred off the axis, from AP +
    lateral and from five views: centre and radii within 0.5 mm (the voxels are 0.5 mm, the
    detector's pixels 1.07 mm at the axis) on the middle slices, where the cone's lines are
    nearly in the slice."""
    from clgs.shape.limb import scan_outline

    e = scan_outline(_cylinder_scan(angles))
    mid = slice(3, 9)
    assert e.valid[mid].all()
    np.testing.assert_allclose(e.centre[mid], [[6.0, -4.0]] * 6, atol=0.5)
    np.testing.assert_allclose(e.radii[mid], [[30.0, 20.0]] * 6, atol=0.5)


def test_a_truncated_view_measures_no_outline():
    """A detector narrower than the cylinder's shadow: every row's silhouette reaches its side,
    no slice is measured."""
    from clgs.shape.limb import scan_outline

    e = scan_outline(_cylinder_scan(AP_LAT, det_u=40))
    assert not e.valid.any()


def test_the_warp_carries_the_scans_outline_onto_the_atlases_and_back():
    """LimbWarp's algebra on known outlines: the scan's ellipse edge lands on the atlas's (placed
    with the tissue's scaling about a centre), ``from_atlas`` undoes ``to_atlas``, no blend is the
    identity, and unmeasured slices (the scan's last ones) carry nothing; factors beyond
    MAX_RATIO are not taken."""
    from clgs.shape.limb import MAX_RATIO, Ellipses, LimbWarp

    z = np.arange(0.0, 200.0, 5.0)
    n = len(z)
    valid = np.ones(n, bool)
    valid[30:] = False
    scan = Ellipses(z, np.tile([4.0, -2.0], (n, 1)), np.tile([50.0, 40.0], (n, 1)), valid)
    atlas = Ellipses(z, np.tile([0.0, 1.0], (n, 1)), np.tile([55.0, 46.0], (n, 1)), np.ones(n, bool))
    warp = LimbWarp(scan, atlas, template=None, variance=1e-6)
    assert warp.measured == pytest.approx(0.75)
    placed = warp.placed(np.array([0.0, 0.0, 100.0]), 1.0, 1.0)
    np.testing.assert_allclose(placed["ratio"][5], [1.1, 1.15])
    pts = np.array([[54.0, -2.0, 50.0], [4.0, 38.0, 60.0], [10.0, 5.0, 20.0]])
    moved, w = warp.to_atlas(placed, pts, np.ones(3))
    np.testing.assert_allclose(moved[0], [55.0, 1.0, 50.0], atol=1e-9)  # the +x edge on the atlas's
    np.testing.assert_allclose(moved[1], [0.0, 47.0, 60.0], atol=1e-9)  # the +y edge
    np.testing.assert_allclose(w, 1.0)
    back, factor = warp.from_atlas(placed, moved, np.ones(3))
    np.testing.assert_allclose(back, pts, atol=1e-9)
    np.testing.assert_allclose(factor, [[1 / 1.1, 1 / 1.15]] * 3)
    same, w0 = warp.to_atlas(placed, pts, np.zeros(3))
    np.testing.assert_array_equal(same, pts)
    assert not w0.any()
    far = np.array([[54.0, -2.0, 195.0]])
    still, wf = warp.to_atlas(placed, far, np.ones(1))
    np.testing.assert_allclose(still, far, atol=1e-6)
    assert wf[0] < 1e-6
    # the atlas's outline placed for a larger limb: twice across about the centre
    twice = warp.placed(np.array([0.0, 0.0, 100.0]), 2.0, 1.0)
    np.testing.assert_allclose(twice["ratio"][5], [1.0, 1.0], atol=1e-12)  # 110/50 > MAX_RATIO: not taken
    assert MAX_RATIO < 110.0 / 50.0


# ---------------------------------------------------------------------------------------- the run
def _limb_geometry(angles):
    return Geometry(DSD=600.0, DSO=400.0, nDetector=(48, 80), dDetector=(1.6, 1.6), nVoxel=(32, 40, 40),
                    dVoxel=(2.0, 2.0, 2.0), angles=np.asarray(angles, float))


@pytest.fixture(scope="module")
def wide_atlas(template):
    """The ellipsoid bone (0.05/mm) in a limb (0.01/mm) of radii (38, 34) mm about the z axis, on a
    grid wider than the template's (so the limb's edge is inside it), variance 1e-6 inside the
    limb and 1e-4 within 2 mm of its edge (the population's spread of edges)."""
    from clgs.shape.model import DensityAtlas

    lo, hi = template.bounds()
    grid = Grid((int((hi[2] - lo[2]) / 2) + 1, 51, 51), (-50.0, -50.0, float(lo[2])), (2.0, 2.0, 2.0))
    pts = grid.points()
    r = np.sqrt((pts[..., 0] / 38.0) ** 2 + (pts[..., 1] / 34.0) ** 2)
    bone = template.sdf_at(pts) < 0
    mean = np.where(bone, 0.05, np.where(r <= 1.0, 0.01, 0.0)).astype(np.float32)
    var = np.where(np.abs(r - 1.0) * 36.0 < 2.0, 1e-4, 1e-6).astype(np.float32)
    return DensityAtlas(mean, var, (2.0, 2.0, 2.0), (float(lo[2]), -50.0, -50.0))


def _narrow_limb_scan(template, angles):
    """The ellipsoid bone in a limb of radii (32, 28) mm centred at (2, -1) mm: narrower than the
    atlas's (38, 34)."""
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector

    geo = _limb_geometry(angles)
    pts = geo.volume_grid(scene=False).points()
    r = np.sqrt(((pts[..., 0] - 2.0) / 32.0) ** 2 + ((pts[..., 1] + 1.0) / 28.0) ** 2)
    truth = np.where(template.sdf_at(pts) < 0, 0.05, np.where(r <= 1.0, 0.01, 0.0)).astype(np.float32)
    return Scan(geo, np.asarray(CTProjector(geo).forward(truth), np.float32), truth=truth)


def _prior(result):
    from clgs.shape.priors import DensityPrior

    (prior,) = [t.fn for t in result.trainer.losses if isinstance(t.fn, DensityPrior)]
    return prior


@pytest.mark.parametrize("angles", [AP_LAT, FIVE])
def test_the_run_starts_its_tissue_in_the_scans_limb_and_holds_the_edge_there(template, shape_model, wide_atlas,
                                                                              angles):
    """A limb narrower than the atlas's, from AP + lateral and from five views: with the default
    ``limb_outline="auto"`` the free Gaussians start inside the scan's limb (elliptic radius at most
    1.08 of the truth's; the atlas's own limb, ``"off"``, puts them out beyond 1.12), and the density
    prior reads air 3 mm outside the scan's edge (the atlas's tissue with "off"), with the
    variance there capped at the limb's inside. (The size is not fitted: this limb, unlike the
    atlas's, runs past the template's ends, which a size search reads as a longer bone.)"""
    import torch

    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _narrow_limb_scan(template, angles)
    parts = AnatomyParts(template, shape_model, wide_atlas)
    kw = _small(alpha_freeze=3, alpha_init_iterations=0, fit_size="off")
    runs = {m: reconstruct_shape_guided(scan, parts, None, iterations=1, limb_outline=m, **kw)
            for m in ("auto", "off")}
    reach = {}
    for m, res in runs.items():
        free = res.trainer.sets[1]
        c = scan.geometry.scene_to_world(free.params["means"].detach().numpy())
        c = c[np.abs(c[:, 2]) < 15.0]  # the middle slices (the detector's rows do not reach the grid's ends)
        reach[m] = float(np.sqrt(((c[:, 0] - 2.0) / 32.0) ** 2 + ((c[:, 1] + 1.0) / 28.0) ** 2).max())
    assert reach["auto"] < 1.08 < 1.12 < reach["off"], reach
    assert _prior(runs["off"]).limb is None
    outside = torch.tensor([[2.0 + 35.0, -1.0, 0.0], [2.0, -1.0 - 31.0, 5.0]], dtype=torch.float32)
    inside = torch.tensor([[2.0 + 25.0, -1.0, 0.0]], dtype=torch.float32)
    for m, res in runs.items():
        prior, s = _prior(res), res.trainer.sets[0]
        mean, var, _, _ = prior._read(s, outside)
        mean_in, _, _, _ = prior._read(s, inside)
        assert float(mean_in[0]) == pytest.approx(0.01, abs=1e-3)
        if m == "auto":
            assert float(mean.max()) < 1e-3 and float(var.max()) <= 1e-6 * (1 + 1e-6)
        else:
            assert float(mean.min()) > 0.005  # the atlas's tissue (near its edge: interpolated)


def test_a_run_with_the_outline_resumes_bit_for_bit(template, shape_model, wide_atlas, tmp_path):
    """The outline is measured again from the scan when a run resumes (nothing of it is kept but
    the setting): a resumed run continues the straight run to the bit."""
    from clgs.methods.shape_guided import reconstruct_shape_guided

    scan = _narrow_limb_scan(template, AP_LAT)
    parts = AnatomyParts(template, shape_model, wide_atlas)
    kw = _small(alpha_freeze=3, fit_size="off")
    kw.pop("checkpoint_every")
    full = reconstruct_shape_guided(scan, parts, tmp_path / "a", iterations=20, checkpoint_every=10, **kw)
    assert _prior(full).limb is not None
    reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=10, checkpoint_every=10,
                             schedule_iterations=20, **kw)
    resumed = reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=20, resume=True, progress=False)
    np.testing.assert_array_equal(full.volume, resumed.volume)


def test_a_truncated_scan_keeps_the_atlases_limb(template, shape_model, wide_atlas, capsys):
    """Where the limb's shadow is wider than the detector the outline is not measured: the run
    says so and keeps the atlas's own limb (no carry in the prior)."""
    from clgs.io.scan import Scan
    from clgs.methods.shape_guided import reconstruct_shape_guided
    from clgs.ops.ct_projector import CTProjector

    full = _narrow_limb_scan(template, AP_LAT)
    geo = Geometry(DSD=600.0, DSO=400.0, nDetector=(48, 24), dDetector=(1.6, 1.6), nVoxel=(32, 40, 40),
                   dVoxel=(2.0, 2.0, 2.0), angles=AP_LAT)
    scan = Scan(geo, np.asarray(CTProjector(geo).forward(full.truth), np.float32), truth=full.truth)
    res = reconstruct_shape_guided(scan, AnatomyParts(template, shape_model, wide_atlas), None, iterations=1,
                                   **_small(alpha_freeze=3, alpha_init_iterations=0, fit_size="off"))
    assert _prior(res).limb is None
    assert "the limb's outline was measured on 0 % of the slices" in capsys.readouterr().err


def test_experiment_records_name_the_limb_outline_and_older_ones_count_as_without(tmp_path):
    """A resumed experiment must not keep a shape-guided record made before the limb's outline
    beside runs with it: older records count as ``limb_outline="off"``; the runs without the
    density prior (which carries the outline) do not name it."""
    from clgs.errors import InputError
    from clgs.experiment import _check_same_run, _made_with

    want = _made_with("shape", 1000, 0, {}, "same")
    assert want["limb_outline"] == "auto"
    old = {"iterations": 1000, "seed": 0, "settings": {}, "fit_size": "on", "fit_length": "auto", "schedule": "fast",
           "lambda_shape": 0.0}
    with pytest.raises(InputError, match="limb_outline 'off', this run asks for 'auto'"):
        _check_same_run(tmp_path / "run.json", old, want)
    _check_same_run(tmp_path / "run.json", old, _made_with("shape", 1000, 0, {"shape": {"limb_outline": "off"}},
                                                           "same"))
    assert "limb_outline" not in _made_with("init+shape", 1000, 0, {}, "same")


def test_the_priors_blend_is_the_warps_inside_and_beyond_the_templates_grid(template, wide_atlas):
    """The density prior reads the carry's blend from the template's distance in torch (bilinear,
    the grid's border plus the way out beyond it); the start's, :meth:`LimbWarp.blend`, from
    ``Template.sdf_at``: the same within 0.05 on points near the bone, across the blend's ramp and
    beyond the template's grid. With equal outlines the carry moves nothing."""
    import torch

    from clgs.shape.limb import Ellipses, LimbWarp
    from clgs.shape.priors import DensityPrior

    z = np.arange(-40.0, 41.0, 2.0)
    same = Ellipses(z, np.zeros((len(z), 2)), np.tile([30.0, 26.0], (len(z), 1)), np.ones(len(z), bool))
    warp = LimbWarp(same, same, template, 1e-6)
    prior = DensityPrior(wide_atlas, template, _limb_geometry(AP_LAT), 1.0, 0.05, 8, field="all", limb=warp)
    rng = np.random.default_rng(5)
    pts = np.concatenate([rng.uniform(-45, 45, (400, 3)) * [1, 1, 0.6], [[16.0, 0, 0], [24.0, 0, 0], [40.0, 0, 0]]])
    x = torch.as_tensor(pts, dtype=torch.float64)
    moved, weight = prior._carried(object(), x, x)
    np.testing.assert_allclose(weight.numpy(), warp.blend(pts), atol=0.05)
    np.testing.assert_allclose(moved.numpy(), pts, atol=1e-9)
    assert weight[-3] < 0.2 and weight[-1] == 1.0
