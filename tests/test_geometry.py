"""Scanner geometry: validation errors, scene mapping and the ray convention."""
import numpy as np
import pytest

from clgs.geometry import Geometry, GeometryError, Grid


def geo(**kw):
    base = dict(DSD=1500.0, DSO=1000.0, nDetector=(64, 80), dDetector=(1.0, 1.0), nVoxel=(32, 40, 48),
                dVoxel=(1.0, 1.0, 1.0), angles=np.linspace(0, np.pi, 5, endpoint=False))
    base.update(kw)
    return Geometry(**base)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(DSO=1600.0), "must be smaller than DSD"),
        (dict(dVoxel=(1, -1, 1)), "dVoxel"),
        (dict(dDetector=(0, 1)), "dDetector"),
        (dict(angles=[]), "empty"),
        (dict(nVoxel=(3, 3)), "3 entries"),
        (dict(nDetector=(0, 4)), "nDetector"),
        (dict(angles=[0.0, np.nan]), "NaN"),
        (dict(mode="fan"), "mode"),
        (dict(DSO=10.0, DSD=20.0), "reaches the source orbit"),
    ],
)
def test_bad_geometry_is_a_clear_error(kw, message):
    with pytest.raises(GeometryError, match=message):
        geo(**kw)


def test_scene_maps_longest_side_to_two():
    g = geo(offOrigin=(5.0, -3.0, 2.0))
    assert g.scale == pytest.approx(2.0 / 48.0)
    grid = g.volume_grid()
    pts = grid.points()
    assert pts.shape == (32, 40, 48, 3)
    # voxel centres span [-1 + h, 1 - h] along x, the longest axis
    assert pts[..., 0].min() == pytest.approx(-1 + grid.spacing[0] / 2)
    assert pts[..., 0].max() == pytest.approx(1 - grid.spacing[0] / 2)
    w = g.scene_to_world(pts[3, 4, 5])
    np.testing.assert_allclose(g.world_to_scene(w), pts[3, 4, 5])
    # offOrigin is (Z, Y, X); world points are (x, y, z)
    np.testing.assert_allclose(g.scene_to_world([0, 0, 0]), [2.0, -3.0, 5.0])


def test_cone_rays_start_at_source_and_hit_pixels():
    g = geo(angles=[0.3])
    o, d = g.rays(0, scene=False)
    src = 1000.0 * np.array([np.cos(0.3), np.sin(0.3), 0])
    np.testing.assert_allclose(o[10, 20], src)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    # central ray goes through the rotation axis towards the detector centre
    g1 = geo(angles=[0.3], nDetector=(65, 81))
    o, d = g1.rays(0, scene=False)
    np.testing.assert_allclose(d[32, 40], -src / 1000.0, atol=1e-12)
    # row index grows with z, column index with e_u = (-sin, cos, 0)
    assert d[40, 40, 2] > 0 and d[20, 40, 2] < 0
    assert np.dot(d[32, 60], [-np.sin(0.3), np.cos(0.3), 0]) > 0


def test_parallel_rays_share_direction():
    g = geo(mode="parallel", angles=[1.0])
    o, d = g.rays(0)
    np.testing.assert_allclose(d, np.broadcast_to(-np.array([np.cos(1.0), np.sin(1.0), 0]), d.shape))
    # neighbouring pixel origins are one pixel (in scene units) apart
    np.testing.assert_allclose(np.linalg.norm(o[0, 1] - o[0, 0]), g.scale * 1.0)


def test_json_round_trip():
    g = geo(offDetector=(1.5, -2.0), mode="parallel")
    g2 = Geometry.from_dict(__import__("json").loads(g.to_json()))
    assert g2.to_dict() == g.to_dict()


def test_grid_block():
    grid = Grid((8, 8, 8), (0.0, 0.0, 0.0), (0.5, 0.5, 0.5))
    b = grid.block((1, 2, 3), (2, 2, 2))
    np.testing.assert_allclose(b.origin, (1.5, 1.0, 0.5))
    with pytest.raises(ValueError):
        grid.block((7, 0, 0), (2, 2, 2))


def test_default_detector_sees_whole_volume():
    g = Geometry.default(n_views=4)
    for v in range(4):
        o, d = g.rays(v)
        # every volume corner projects inside the detector: the corner rays exist within its span
        vec = g.view_vectors()[v]
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        src, det, du, dv = vec[0:3], vec[3:6], vec[6:9], vec[9:12]
        n = np.cross(du, dv)
        for c in corners:
            t = np.dot(det - src, n) / np.dot(c - src, n)
            hit = src + t * (c - src) - det
            u = np.dot(hit, du) / np.dot(du, du)
            vv = np.dot(hit, dv) / np.dot(dv, dv)
            assert abs(u) < g.nDetector[1] / 2 and abs(vv) < g.nDetector[0] / 2


def test_every_detector_sized_to_see_a_volume_uses_the_one_margin(monkeypatch):
    """Geometry.default, clgs simulate's scanner and the anatomies' scenes all size their detector
    as clgs.geometry.DETECTOR_MARGIN times the volume's shadow (they once used 1.05 and 1.04)."""
    from clgs import geometry
    from clgs.anatomy.population import scan_geometry_kwargs
    from clgs.anatomy.simulation import _detector_sized
    from clgs.ct.simulate import scanner_geometry

    grid = Grid((40, 60, 50), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    half_u, half_v = geometry.shadow_half_extents((40.0, 60.0, 50.0), 1000.0, 1500.0, "cone")
    for margin in (geometry.DETECTOR_MARGIN, 1.3):
        monkeypatch.setattr(geometry, "DETECTOR_MARGIN", margin)
        monkeypatch.setattr("clgs.ct.simulate.DETECTOR_MARGIN", margin)
        monkeypatch.setattr("clgs.anatomy.population.DETECTOR_MARGIN", margin)
        sim = scanner_geometry((40, 60, 50), (1.0, 1.0, 1.0), views=4, detector=64)
        assert sim.dDetector[0] * 64 == pytest.approx(2 * margin * max(half_u, half_v))
        kw = scan_geometry_kwargs(grid, pixel_mm=0.5)
        (nv, nu), _ = _detector_sized((40, 60, 50), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0),
                                      {"DSO": 1000.0, "DSD": 1500.0, "dDetector": (0.5, 0.5)}, 64)
        for v, u in (kw["nDetector"], (nv, nu)):
            assert 0 <= v * 0.5 - 2 * margin * half_v < 8 * 0.5 and 0 <= u * 0.5 - 2 * margin * half_u < 8 * 0.5
        assert geometry.Geometry.default(n_voxel=8, volume_mm=100.0).dDetector[0] * 256 == pytest.approx(
            100.0 * np.sqrt(2.0) * 1.5 * margin)
