"""Per-view (vector) geometry: a circular scan written as vectors gives the same numbers through
every operator; the voxel projector pair stays adjoint and matches a plain Joseph reference on
offset, turned, non-circular orbits; Gaussian projections on a tilted and rolled detector match
the quadrature reference, with finite-difference gradients; bad vectors are errors naming the view."""
import json

import numpy as np
import pytest
import torch

from clgs.errors import InputError
from clgs.geometry import Geometry, GeometryError, read_geometry


def circular(mode="cone", n_views=5):
    return Geometry(DSD=120.0, DSO=80.0, nDetector=(11, 23), dDetector=(1.7, 1.6), nVoxel=(13, 17, 19),
                    dVoxel=(1.1, 0.9, 1.0), angles=np.linspace(0.2, 2 * np.pi + 0.2, n_views, endpoint=False),
                    offOrigin=(0.8, -1.3, 0.6), offDetector=(1.1, -2.3), mode=mode)


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def c_arm(mode="cone", yaw_deg=6.0, roll_deg=0.0, pitch_deg=0.0, n_views=5):
    """Irregular views over ~120 degrees, the source distance and height changing from view to view,
    the detector offset and turned (yaw: about its v axis; roll: about its normal; pitch: about u)."""
    rng = np.random.default_rng(7)
    theta = np.deg2rad(np.sort(rng.uniform(-60, 60, n_views)))
    rows = []
    for i, t in enumerate(theta):
        e_s = np.array([np.cos(t), np.sin(t), 0.0])
        e_u = np.array([-np.sin(t), np.cos(t), 0.0])
        e_v = np.array([0.0, 0.0, 1.0])
        normal = np.cross(e_u, e_v)
        turn = _rot(e_v, np.deg2rad(yaw_deg)) @ _rot(normal, np.deg2rad(roll_deg)) @ _rot(e_u, np.deg2rad(pitch_deg))
        u, v = turn @ (1.6 * e_u), turn @ (1.7 * e_v)
        dso = 80.0 + 4.0 * i
        src = dso * e_s + np.array([0.0, 0.0, 1.5 * (i - 2)])
        det = -(125.0 + 3.0 * i - dso) * e_s + 2.1 * e_u - 1.2 * e_v
        rows.append([*(src if mode == "cone" else -e_s), *det, *u, *v])
    return Geometry.from_vectors(rows, nDetector=(11, 23), nVoxel=(13, 17, 19), dVoxel=(1.1, 0.9, 1.0),
                                 offOrigin=(0.8, -1.3, 0.6), mode=mode)


# ----------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_circular_written_as_vectors_is_the_same_scan(mode, tmp_path):
    g = circular(mode)
    v = g.as_vectors()
    assert g.is_circular and not v.is_circular
    # two float64 derivations of the same numbers: equal to rounding, not bit for bit (numpy's
    # trigonometry may differ in the last bit between code paths on some CPUs); the kernels are
    # checked bit for bit below, where they are fed identical records
    close = dict(rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(v.view_vectors(), g.view_vectors(), **close)
    np.testing.assert_allclose(v.view_vectors(scene=False, views=[3, 1]), g.view_vectors(scene=False, views=[3, 1]),
                               **close)
    np.testing.assert_allclose(v.rays(2)[1], g.rays(2)[1], **close)
    assert v.volume_grid() == g.volume_grid() and v.scale == g.scale
    assert v.resolution_mm == pytest.approx(g.resolution_mm, rel=1e-12)
    np.testing.assert_allclose(v.source_detector_distance(), g.source_detector_distance(), rtol=1e-12)
    np.testing.assert_allclose(np.mod(v.angles, 2 * np.pi), np.mod(g.angles, 2 * np.pi), atol=1e-12)
    if mode == "cone":
        assert (pytest.approx(np.hypot(80.0, 0)), pytest.approx(120.0)) == (v.DSO, v.DSD)
    # JSON: TIGRE's names for the circular scan, a vectors key (and no angles) for the per-view one
    d = v.to_dict()
    assert "vectors" in d and "angles" not in d and "DSO" not in d
    assert "angles" in g.to_dict() and "vectors" not in g.to_dict()
    back = Geometry.from_dict(json.loads(json.dumps(d)))
    np.testing.assert_array_equal(back.view_vectors(), v.view_vectors())
    assert back == v and back != g
    path = tmp_path / "geometry.json"
    path.write_text(json.dumps(d))
    np.testing.assert_array_equal(read_geometry(path).view_vectors(), v.view_vectors())
    # a subset keeps its views' vectors
    np.testing.assert_allclose(v.select([4, 0]).view_vectors(), g.select([4, 0]).view_vectors(), **close)


def test_an_isocentre_places_the_vectors_as_it_places_a_circular_scan(rng):
    """The vectors share the scanner's frame (offOrigin's); the isocentre moves both into the world."""
    from clgs.ops.ct_projector import CTProjector

    g = Geometry.from_dict({**circular().to_dict(), "isocentre": [40.0, -25.0, 130.0]})
    v = g.as_vectors()
    np.testing.assert_array_equal(v.view_vectors(), g.view_vectors())
    np.testing.assert_array_equal(v.view_vectors(scene=False), g.view_vectors(scene=False))
    np.testing.assert_array_equal(v.frame_vectors(), circular().view_vectors(scene=False))
    assert v.volume_grid(scene=False) == g.volume_grid(scene=False)
    back = Geometry.from_dict(json.loads(json.dumps(v.to_dict())))
    assert back.isocentre == (40.0, -25.0, 130.0) and back == v
    x = rng.random(g.nVoxel)
    np.testing.assert_array_equal(CTProjector(v).forward(x), CTProjector(g).forward(x))
    # the world shift only rounds differently
    np.testing.assert_allclose(CTProjector(v).forward(x), CTProjector(circular()).forward(x), rtol=1e-12, atol=1e-12)


def test_a_scan_folder_keeps_its_vectors(tmp_path):
    from clgs.io.scan import Scan

    g = c_arm()
    proj = np.ones(g.projection_shape, np.float32)
    Scan(g, proj).save(tmp_path / "scan")
    back = Scan.load(tmp_path / "scan")
    assert not back.geometry.is_circular
    np.testing.assert_array_equal(back.geometry.view_vectors(), g.view_vectors())
    sub = back.subset([1, 3])
    np.testing.assert_array_equal(sub.geometry.view_vectors(), g.view_vectors(views=[1, 3]))
    # the scan.json itself is a geometry file
    assert read_geometry(tmp_path / "scan" / "scan.json") == g


def _bad(view, first, last, value):
    rows = c_arm().view_vectors(scene=False).copy()
    rows[view, first:last] = value
    return rows


@pytest.mark.parametrize("view, first, last, value, message", [
    (2, 4, 5, np.nan, "view 2: the vector has NaN"),
    (1, 6, 9, 0.0, "view 1: zero-length pixel step along u"),
    (3, 9, 12, 0.0, "view 3: zero-length pixel step along v"),
    (0, 9, 12, [0.0, 3.2, 0.0], "view 0: the u and v pixel steps are parallel"),
    (4, 0, 3, [0.5, 0.2, 0.1], "view 4: the source .* lies inside the volume"),
])
def test_bad_vectors_name_the_view(view, first, last, value, message):  # noqa: PLR0913
    rows = _bad(view, first, last, value)
    if "parallel" in message:  # v a multiple of u
        rows[0, 9:12] = 2.0 * rows[0, 6:9]
    with pytest.raises(GeometryError, match=message):
        Geometry.from_vectors(rows, (11, 23), (13, 17, 19), (1.1, 0.9, 1.0), (0.8, -1.3, 0.6))


def test_more_bad_vectors():
    rows = c_arm().view_vectors(scene=False)
    grid = dict(nDetector=(11, 23), nVoxel=(13, 17, 19), dVoxel=(1.1, 0.9, 1.0), offOrigin=(0.8, -1.3, 0.6))
    on_plane = rows.copy()
    on_plane[1, 0:3] = on_plane[1, 3:6] + 5.0 * on_plane[1, 6:9] - 3.0 * on_plane[1, 9:12]
    with pytest.raises(GeometryError, match="view 1: the source .* lies on the detector plane"):
        Geometry.from_vectors(on_plane, **grid)
    skew = rows.copy()
    skew[2, 9:12] += 0.2 * skew[2, 6:9]
    with pytest.raises(GeometryError, match="view 2: .* not perpendicular"):
        Geometry.from_vectors(skew, **grid)
    with pytest.raises(GeometryError, match=r"shape \(n_views, 12\)"):
        Geometry.from_vectors(rows[:, :11], **grid)
    with pytest.raises(GeometryError, match="view 4: the parallel rays are not perpendicular"):
        oblique = c_arm("parallel", 0.0).view_vectors(scene=False)
        oblique[4, 2] = 0.1
        Geometry.from_vectors(oblique, mode="parallel", **grid)
    with pytest.raises(GeometryError, match="view 0: zero-length ray direction"):
        par = c_arm("parallel", 0.0).view_vectors(scene=False)
        par[0, 0:3] = 0
        Geometry.from_vectors(par, mode="parallel", **grid)
    d = c_arm().to_dict()
    d["angles"] = [0.0, 1.0]
    with pytest.raises(GeometryError, match="2 angles but 5 vectors"):
        Geometry.from_dict(d)
    with pytest.raises(GeometryError, match="no angles to replace"):
        c_arm().with_angles([0.0])


def test_a_view_count_that_differs_from_the_images_is_an_error():
    from clgs.io.validate import ScanError, check_projections

    g = c_arm()
    with pytest.raises(ScanError, match=r"scan\.npy: shape \(4, 11, 23\) does not match .* \(angles or vectors\)"):
        check_projections(np.ones((4, 11, 23), np.float32), g, source="scan.npy")


def test_geometry_file_errors_name_the_file(tmp_path):
    p = tmp_path / "g.json"
    d = c_arm().to_dict()
    d["vectors"][3][7] = 0.0
    d["vectors"][3][6] = 0.0
    d["vectors"][3][8] = 0.0
    p.write_text(json.dumps(d))
    with pytest.raises(GeometryError, match=r"g\.json: view 3: zero-length pixel step"):
        read_geometry(p)
    p.write_text("{")
    with pytest.raises(GeometryError, match=r"g\.json: not a JSON file"):
        read_geometry(p)


def test_fdk_takes_vectors_and_a_circular_scan_as_vectors_gives_the_circular_fdk(rng):
    """(tests/test_ct_fdk_vectors.py checks FDK on vectors in full.)"""
    from clgs.ct.fdk import fdk

    g = circular()
    p = np.abs(rng.standard_normal(g.projection_shape))
    a, b = fdk(p, g, dtype=np.float64), fdk(p, g.as_vectors(), dtype=np.float64)
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * np.abs(a).max())
    assert np.isfinite(fdk(np.zeros(c_arm().projection_shape, np.float32), c_arm())).all()


# ----------------------------------------------------------------------------- voxel projector pair
@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_ct_projector_and_sart_give_the_same_bits_on_circular_vectors(mode, rng):
    from clgs.ct.sart import sart
    from clgs.ops.ct_projector import CTProjector

    g = circular(mode)
    v = g.as_vectors()
    x = rng.random(g.nVoxel).astype(np.float32)
    y = rng.random(g.projection_shape).astype(np.float32)
    Pg, Pv = CTProjector(g), CTProjector(v)
    np.testing.assert_array_equal(Pv.forward(x), Pg.forward(x))
    np.testing.assert_array_equal(Pv.backward(y), Pg.backward(y))
    b = Pg.forward(x)
    np.testing.assert_array_equal(sart(b, v, n_iter=2, subsets=2), sart(b, g, n_iter=2, subsets=2))


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_ct_pair_is_adjoint_and_right_on_a_c_arm_orbit(mode, rng):
    from test_ct_projector import joseph_reference

    from clgs.ops.ct_projector import CTProjector

    g = c_arm(mode, yaw_deg=8.0 if mode == "cone" else 0.0)  # parallel rays stay perpendicular to the detector
    P = CTProjector(g)
    x = rng.random(g.nVoxel)
    y = rng.random(g.projection_shape)
    ax, aty = P.forward(x), P.backward(y)
    assert ax.dtype == np.float64
    lhs, rhs = np.sum(ax * y), np.sum(x * aty)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
    ref = joseph_reference(x, g)
    assert float(ref.max()) > 5.0  # the rays cross the volume
    np.testing.assert_allclose(ax, ref, rtol=1e-9, atol=1e-9 * float(ref.max()))
    # float32 agrees with the double build
    np.testing.assert_allclose(P.forward(x.astype(np.float32)), ax, rtol=1e-4, atol=1e-5 * float(ax.max()))


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_ct_pair_takes_a_rolled_and_pitched_detector_through_an_upright_stand_in(mode, rng):
    """Exact transpose (double precision); forward within 1.5 % of a smooth blob's peak of Joseph's
    method on the real rays (interpolation on the virtual detector, see clgs.ops.ct_upright)."""
    from test_ct_projector import joseph_reference

    from clgs.ops.ct_projector import CTProjector

    turn = dict(yaw_deg=7.0, roll_deg=11.0, pitch_deg=-9.0) if mode == "cone" else dict(yaw_deg=0.0, roll_deg=11.0)
    g = c_arm(mode, **turn)
    P = CTProjector(g)
    assert P._upright is not None
    x = rng.random(g.nVoxel)
    y = rng.random(g.projection_shape)
    ax, aty = P.forward(x), P.backward(y)
    lhs, rhs = np.sum(ax * y), np.sum(x * aty)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
    sub = [4, 1]
    np.testing.assert_array_equal(P.forward(x, views=sub), ax[sub])
    assert abs(np.sum(P.forward(x, views=sub) * y[sub]) - np.sum(x * P.backward(y[sub], views=sub))) <= 1e-12 * abs(lhs)
    z, yy, xx = np.mgrid[:13, :17, :19]
    blob = np.exp(-((z - 6) ** 2 / 8 + (yy - 8) ** 2 / 12 + (xx - 9) ** 2 / 14))
    ref = joseph_reference(blob, g)
    err = np.abs(P.forward(blob) - ref).max() / ref.max()
    assert err < 0.015, err
    # float32 runs too, and agrees
    np.testing.assert_allclose(P.forward(blob.astype(np.float32)), P.forward(blob), rtol=1e-4, atol=1e-5 * ref.max())


def test_ct_projector_refuses_what_it_cannot_take_naming_the_view():
    from clgs.ops.ct_projector import CTProjector

    vec = c_arm("parallel", 0.0).view_vectors(scene=False)
    # parallel rays with a vertical part (perpendicular to a pitched detector)
    turn = np.deg2rad(10.0)
    for i in (2,):
        r, v = vec[i, 0:3].copy(), vec[i, 9:12].copy()
        vec[i, 0:3] = np.cos(turn) * r + np.sin(turn) * np.array([0, 0, 1.0])
        vec[i, 9:12] = np.linalg.norm(v) * (np.cos(turn) * np.array([0, 0, 1.0]) - np.sin(turn) * r)
    g = Geometry.from_vectors(vec, (11, 23), (13, 17, 19), (1.1, 0.9, 1.0), (0.8, -1.3, 0.6), mode="parallel")
    with pytest.raises(InputError, match="view 2: parallel rays with a vertical part"):
        CTProjector(g)


@pytest.mark.parametrize("turn", [dict(yaw_deg=8.0), dict(yaw_deg=8.0, roll_deg=10.0, pitch_deg=5.0)])
def test_sart_reconstructs_a_c_arm_scan(turn):
    """SART on the C-arm orbit (detector turned, then also rolled and pitched) recovers a
    consistent volume: its reprojection error falls ten-fold."""
    from clgs.ct.sart import sart
    from clgs.ops.ct_projector import CTProjector

    g = c_arm(**turn)
    P = CTProjector(g)
    truth = np.zeros(g.nVoxel, np.float32)
    truth[4:9, 5:12, 6:13] = 0.05
    b = P.forward(truth)
    x = sart(b, g, n_iter=20)
    assert np.linalg.norm(P.forward(x) - b) < 0.1 * np.linalg.norm(b)


# ----------------------------------------------------------------------------- Gaussian projector
def _scene(n, seed=0, lo=0.1, hi=0.25, spread=0.8):
    gen = torch.Generator().manual_seed(seed)
    m = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * spread
    s = lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    d = 0.2 + torch.rand(n, generator=gen, dtype=torch.float64)
    return m, s, q, d


@pytest.mark.parametrize("mode", ["affine", "exact"])
@pytest.mark.parametrize("beam", ["cone", "parallel"])
def test_gaussian_projector_gives_the_same_bits_on_circular_vectors(beam, mode):
    from clgs.ops.projector import project

    g = circular(beam)
    v = g.as_vectors()
    m, s, q, d = _scene(30, spread=1.2, lo=0.03, hi=0.1)
    for dtype in (torch.float32, torch.float64):
        args_g = [t.to(dtype).clone().requires_grad_() for t in (m, s, q, d)]
        args_v = [t.to(dtype).clone().requires_grad_() for t in (m, s, q, d)]
        out_g = project(*args_g, g, None, mode)
        out_v = project(*args_v, v, None, mode)
        assert float(out_g.detach().max()) > 0.1
        assert torch.equal(out_g, out_v)
        w = torch.rand(out_g.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
        (out_g * w).sum().backward()
        (out_v * w).sum().backward()
        for a, b in zip(args_g, args_v):
            assert torch.equal(a.grad, b.grad)


@pytest.mark.parametrize("beam", ["cone", "parallel"])
def test_gaussian_projection_on_a_tilted_detector_matches_the_references(beam):
    """Exact mode against trapezoid integration along every pixel's own ray (geometry.rays), and
    both modes against the dense reference, on a detector turned about all three of its axes."""
    from clgs.ops.projector import project_packed
    from clgs.reference.gaussians import covariance, precision
    from clgs.reference.projection import exact_quadrature, project_dense, ray_min_q

    # parallel beam: rays perpendicular to the detector, so it turns in its own plane only
    g = c_arm(beam, yaw_deg=7.0, roll_deg=11.0, pitch_deg=-9.0) if beam == "cone" else c_arm(beam, 0.0, 11.0, 0.0)
    m, s, q, d = _scene(4, seed=5)
    P = precision(s, q)
    for view in (0, 3):
        out = project_packed(m, P, d, g, [view], "exact")[0].numpy()
        quad = exact_quadrature(m.numpy(), P, d.numpy(), g, view)
        qs = ray_min_q(m.numpy(), P, g, view)
        clear = (np.abs(qs - 9.0) > 0.3).all(0)
        expect = (quad * (qs <= 9.0)).sum(0)
        assert (expect[clear] > 0).sum() > 30
        np.testing.assert_allclose(out[clear], expect[clear], rtol=1e-6, atol=1e-9 * expect.max())
    for mode, mats in (("exact", P), ("affine", covariance(s, q))):
        ref, near = project_dense(m, mats, d, g, [0, 2, 4], mode)
        out = project_packed(m, mats, d, g, [0, 2, 4], mode)
        assert float(ref.max()) > 0.5
        assert float((out - ref)[~near].abs().max()) < 1e-10 * float(ref.abs().max())


@pytest.mark.parametrize("mode", ["affine", "exact"])
def test_gradcheck_on_a_tilted_detector(mode):
    from clgs.ops.projector import project

    g = c_arm("cone", yaw_deg=7.0, roll_deg=11.0, pitch_deg=-9.0)
    small = Geometry.from_vectors(g.view_vectors(scene=False) * np.r_[np.ones(6), np.full(6, 2.0)],
                                  nDetector=(6, 12), nVoxel=g.nVoxel, dVoxel=g.dVoxel, offOrigin=g.offOrigin)
    m, s, q, d = _scene(3, seed=11, lo=0.12, hi=0.25, spread=0.6)
    args = [t.clone().requires_grad_() for t in (m, s, q, d)]
    assert float(project(*args, small, [1, 3], mode).detach().max()) > 0.1
    f = lambda *a: project(*a, small, [1, 3], mode)  # noqa: E731
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_densification_statistic_matches_on_circular_vectors():
    from clgs.fit.gaussians import Densifier

    g = circular()
    m, _, _, _ = _scene(50, spread=1.0)
    grad = torch.randn(50, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    a = Densifier(g).view_space_grad(m, grad, 2)
    b = Densifier(g.as_vectors()).view_space_grad(m, grad, 2)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=0)
    # a per-view detector: the statistic follows each view's own source distance
    v = c_arm()
    dsd = v.source_detector_distance()
    assert dsd.max() - dsd.min() > 10.0
    np.testing.assert_allclose(Densifier(v)._dsd, dsd * v.scale, rtol=1e-12)
