"""Metrics against hand-computed values and an independent torch reference of R2-Gaussian's SSIM;
surfaces and surface distances against analytic spheres."""
import math

import numpy as np
import pytest
import torch

from clgs import metrics
from clgs.mesh.surface import (
    SurfaceError,
    point_to_mesh_distance,
    sample_surface,
    surface_distance,
    surface_from_volume,
)
from clgs.metrics import MetricError


def ssim2d_reference(a, b):
    """R2-Gaussian's 2-D SSIM written out in torch: 11x11 Gaussian (sigma 1.5), zero padding, mean."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-x ** 2 / (2 * 1.5 ** 2))
    g = g / g.sum()
    w = (g[:, None] * g[None, :])[None, None]
    a = torch.as_tensor(a, dtype=torch.float64)[None, None]
    b = torch.as_tensor(b, dtype=torch.float64)[None, None]
    conv = lambda t: torch.nn.functional.conv2d(t, w, padding=5)  # noqa: E731
    ma, mb = conv(a), conv(b)
    saa, sbb, sab = conv(a * a) - ma ** 2, conv(b * b) - mb ** 2, conv(a * b) - ma * mb
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * ma * mb + c1) * (2 * sab + c2)) / ((ma ** 2 + mb ** 2 + c1) * (saa + sbb + c2))
    return float(m.mean())


def ssim3d_reference(pred, truth):
    axes = []
    for axis in range(3):
        vals = [ssim2d_reference(np.take(pred, i, axis), np.take(truth, i, axis))
                for i in range(truth.shape[axis]) if np.take(truth, i, axis).max() > 0]
        axes.append(np.mean(vals))
    return np.mean(axes), axes


@pytest.fixture
def pair(rng):
    truth = np.zeros((14, 16, 18), np.float32)
    zz, yy, xx = np.mgrid[:14, :16, :18]
    truth[((zz - 7) ** 2 + (yy - 8) ** 2 + (xx - 9) ** 2) < 30] = 1.0
    truth[2:5, 3:9, 4:12] += 0.5
    truth[0] = 0  # an empty slice along z: skipped by the SSIM mean
    pred = truth + 0.1 * rng.standard_normal(truth.shape).astype(np.float32)
    return pred, truth


def test_identical_volumes():
    t = np.random.default_rng(0).random((12, 12, 12))
    assert metrics.psnr3d(t, t) == math.inf
    assert metrics.ssim3d(t, t) == pytest.approx(1.0, abs=1e-12)
    assert metrics.masked_psnr3d(t, t, t > 0.5) == math.inf


def test_psnr_known_mse_and_normalisation():
    truth = np.zeros((4, 5, 6))
    truth[1:3, 1:4, 2:5] = 2.0  # range [0, 2]
    pred = truth + 0.2  # 0.1 of the range everywhere: MSE 0.01 -> 20 dB
    assert metrics.psnr3d(pred, truth) == pytest.approx(20.0, abs=1e-9)
    assert metrics.psnr3d(pred + 3.0 - 3.0, truth + 5.0 - 5.0) == pytest.approx(20.0)
    # shifting both by a constant does not change it (min of the truth is subtracted)
    assert metrics.psnr3d(pred + 7, truth + 7) == pytest.approx(20.0, abs=1e-9)
    # raw values (R2-Gaussian's pixel_max = 1): error 0.2 -> 10 log10(1 / 0.04)
    assert metrics.psnr3d(pred, truth, data_range=1.0) == pytest.approx(10 * math.log10(1 / 0.04))
    assert metrics.ssim3d(pred, truth, data_range=2.0) == pytest.approx(metrics.ssim3d(pred, truth), abs=1e-12)
    # masked: error 0.4 (0.2 of the range) inside the mask only -> 10 log10(1/0.04)
    p2 = truth.copy()
    mask = truth > 0
    p2[mask] += 0.4
    assert metrics.masked_psnr3d(p2, truth, mask) == pytest.approx(10 * math.log10(1 / 0.04))
    assert metrics.psnr3d(p2, truth) == pytest.approx(10 * math.log10(1 / (0.04 * mask.mean())))


def test_ssim3d_matches_r2gaussian_reference(pair):
    pred, truth = pair
    ours, axes = metrics.ssim3d(pred, truth, return_axes=True)
    top = truth.max()  # the truth spans [0, 1.5]: metrics see both divided by 1.5
    assert top == pytest.approx(1.5)
    ref, ref_axes = ssim3d_reference(pred.astype(float) / top, truth.astype(float) / top)
    assert ours == pytest.approx(ref, abs=1e-9)
    assert axes == pytest.approx(ref_axes, abs=1e-9)
    assert 0.2 < ours < 0.95


def test_ssim_map_interior_equals_skimage(pair):
    from skimage.metrics import structural_similarity

    pred, truth = pair
    maps = metrics.ssim_maps(pred, truth)
    top = float(truth.max())
    _, full = structural_similarity(truth[7].astype(float) / top, pred[7].astype(float) / top, data_range=1.0,
                                    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, full=True)
    # away from the borders (>= 5 pixels) the padding does not matter: same numbers
    assert np.allclose(maps[0][7][5:-5, 5:-5], full[5:-5, 5:-5], atol=1e-9)
    sk, sk_axes = metrics.ssim3d(pred, truth, implementation="skimage", return_axes=True)
    p, t = pred.astype(float) / top, truth.astype(float) / top
    expected_y = np.mean([structural_similarity(t[:, j], p[:, j], data_range=1.0, gaussian_weights=True, sigma=1.5,
                                                use_sample_covariance=False)
                          for j in range(t.shape[1]) if t[:, j].max() > 0])
    assert sk_axes[1] == pytest.approx(expected_y, abs=1e-9)
    assert sk != pytest.approx(metrics.ssim3d(pred, truth), abs=1e-3)  # borders do differ


def test_masked_ssim_is_mean_of_map_over_mask(pair):
    pred, truth = pair
    mask = truth > 0.5
    maps = metrics.ssim_maps(pred, truth)
    expected = np.mean([m[mask].mean() for m in maps])
    assert metrics.masked_ssim3d(pred, truth, mask) == pytest.approx(expected, abs=1e-12)
    assert metrics.ssim3d(pred, truth, mask=np.ones_like(mask)) == pytest.approx(
        np.mean([m.mean() for m in maps]))


def test_projection_metrics_normalise_each_view():
    rng = np.random.default_rng(5)
    truth = rng.random((3, 12, 13)) + 0.1
    truth[1] *= 10  # per-view normalisation makes the scale irrelevant
    pred = truth * np.array([2.0, 3.0, 0.5])[:, None, None]  # a scaled copy: identical after normalising
    assert metrics.projection_psnr(pred, truth) == math.inf
    assert metrics.projection_ssim(pred, truth) == pytest.approx(1.0)
    pred = truth.copy()
    pred[0] = truth[0] / truth[0].max() + 0.05  # view 0 after normalising: max 1.05
    a = truth[0] / truth[0].max()
    b = pred[0] / pred[0].max()
    mean, per_view = metrics.projection_psnr(pred, truth, per_view=True)
    assert per_view[0] == pytest.approx(10 * math.log10(1 / np.mean((a - b) ** 2)))
    assert per_view[1:] == [math.inf, math.inf]
    _, ssim_views = metrics.projection_ssim(pred, truth, per_view=True)
    assert ssim_views[0] == pytest.approx(ssim2d_reference(b, a), abs=1e-10)


def test_metric_errors():
    t = np.ones((4, 4, 4))
    with pytest.raises(MetricError, match="constant"):
        metrics.psnr3d(t, t)
    with pytest.raises(MetricError, match="same shape"):
        metrics.ssim3d(np.zeros((4, 4, 5)), np.arange(64.0).reshape(4, 4, 4))
    with pytest.raises(MetricError, match="empty"):
        metrics.psnr3d(t, np.arange(64.0).reshape(4, 4, 4), mask=np.zeros((4, 4, 4), bool))
    bad = np.arange(64.0).reshape(4, 4, 4)
    with pytest.raises(MetricError, match="NaN"):
        metrics.psnr3d(bad * np.nan, bad)


# ------------------------------------------------------------------------------ surfaces
def sphere(radius, centre=(0.0, 0.0, 0.0), subdivisions=4):
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return ico.vertices + np.asarray(centre), ico.faces


def test_point_to_mesh_distance_is_exact(rng):
    import trimesh

    v, f = sphere(10.0, subdivisions=2)
    pts = rng.uniform(-20, 20, (300, 3))
    ours = point_to_mesh_distance(pts, (v, f), k=2)  # small k: exercises the widening
    tris = v[f]
    ref = np.array([np.linalg.norm(trimesh.triangles.closest_point(tris, np.repeat(p[None], len(tris), 0)) - p,
                                   axis=1).min() for p in pts])
    assert np.allclose(ours, ref, atol=1e-9)


def test_distances_from_far_away_streaks_are_exact(rng):
    """A streaky few-view reconstruction's surface: small shards scattered up to ~250 mm from the
    bone. Every point is far from every triangle, the case where a nearest-centroid search has
    to prove a great many triangles farther away; the distances stay exact."""
    import trimesh

    bone = sphere(20.0, subdivisions=4)  # a convex polyhedron inscribed in a 20 mm sphere
    centres = rng.uniform(-150, 150, (300, 3))
    centres = centres[np.linalg.norm(centres, axis=1) > 45][:120]
    shard = trimesh.creation.icosphere(subdivisions=1, radius=2.0)
    sv = np.concatenate([shard.vertices + c for c in centres])
    sf = np.concatenate([shard.faces + i * len(shard.vertices) for i in range(len(centres))])
    streaks = (sv, sf)
    n = 5000
    pts = np.concatenate([sample_surface(streaks, n, 0), sv])
    d = point_to_mesh_distance(pts, bone)
    # between the circumscribed sphere (vertices) and the inscribed one (nearest face plane)
    tri = bone[0][bone[1]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    r_in = np.abs(np.einsum("ij,ij->i", normal, tri[:, 0]) / np.linalg.norm(normal, axis=1)).min()
    r = np.linalg.norm(pts, axis=1)
    assert 19.9 < r_in < 20.0 and r.min() > 40.0
    assert np.all(d >= r - 20.0 - 1e-9) and np.all(d <= r - r_in + 1e-9)
    some = rng.choice(len(pts), 60, replace=False)  # and exactly the brute-force minimum
    ref = np.array([np.linalg.norm(trimesh.triangles.closest_point(tri, np.repeat(p[None], len(tri), 0)) - p,
                                   axis=1).min() for p in pts[some]])
    np.testing.assert_allclose(d[some], ref, atol=1e-9)
    sd = surface_distance(streaks, bone, n_samples=n)
    assert sd["mean_ab"] == pytest.approx(d[:n].mean(), rel=1e-12)
    assert sd["hausdorff"] >= d.max() - 1e-9


def test_concentric_spheres_distance():
    a, b = sphere(20.0, subdivisions=3), sphere(23.0)
    d = surface_distance(a, b, n_samples=5000)
    assert d["mean"] == pytest.approx(3.0, abs=0.05)
    assert d["p95"] == pytest.approx(3.0, abs=0.08)
    assert d["hausdorff"] == pytest.approx(3.0, abs=0.1)
    assert d == surface_distance(a, b, n_samples=5000)  # seeded: reproducible
    assert surface_distance(a, a, n_samples=5000)["hausdorff"] == pytest.approx(0.0, abs=1e-9)


def test_surface_from_ball_volume():
    import trimesh

    spacing = (0.8, 1.0, 1.25)  # (dZ, dY, dX)
    origin = (-20.0, -18.0, -15.0)  # centre of voxel [0, 0, 0], (x, y, z)
    shape = (40, 38, 34)
    centre = np.array([1.0, 2.0, 0.5])
    zz, yy, xx = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    world = np.stack([origin[0] + xx * spacing[2], origin[1] + yy * spacing[1], origin[2] + zz * spacing[0]], -1)
    vol = np.linalg.norm(world - centre, axis=-1)  # distance field: level r is a sphere of radius r
    mesh = surface_from_volume(-vol, -10.0, spacing=spacing, origin=origin)
    r = np.linalg.norm(mesh.vertices - centre, axis=1)
    assert np.abs(r - 10.0).max() < 0.1
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert tm.volume > 0  # outward normals
    assert tm.volume == pytest.approx(4 / 3 * np.pi * 1000, rel=0.02)
    d = surface_distance(mesh, sphere(10.0, centre), n_samples=5000)
    assert d["mean"] < 0.05 and d["hausdorff"] < 0.15
    with pytest.raises(SurfaceError, match="outside"):
        surface_from_volume(vol, 1000.0)
    assert len(sample_surface(mesh, 100)) == 100


def test_ssim_slabs_do_not_change_the_result(pair, monkeypatch):
    pred, truth = pair
    mask = truth > 0.5
    whole = metrics.ssim3d(pred, truth, return_axes=True), metrics.masked_ssim3d(pred, truth, mask)
    original = metrics._slabs
    monkeypatch.setattr(metrics, "_slabs", lambda n, size: original(n, size, budget=3 * size))
    sliced = metrics.ssim3d(pred, truth, return_axes=True), metrics.masked_ssim3d(pred, truth, mask)
    assert sliced[0][0] == pytest.approx(whole[0][0], abs=1e-12)
    assert sliced[0][1] == pytest.approx(whole[0][1], abs=1e-12)
    assert sliced[1] == pytest.approx(whole[1], abs=1e-12)
