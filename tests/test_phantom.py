"""Surface -> label -> signed distance -> CT-like density (clgs.anatomy.phantom), on analytic shapes."""
import numpy as np
import pytest
import trimesh

from clgs.anatomy import phantom as ph
from clgs.anatomy.alignment import align_rigid
from clgs.anatomy.population import scan_geometry_kwargs
from clgs.geometry import Grid
from clgs.mesh import voxels as mv


def centred_grid(shape, spacing):
    n = np.asarray(shape[::-1])
    return Grid(tuple(shape), tuple(-0.5 * (n - 1) * spacing), (float(spacing),) * 3)


def rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


# --------------------------------------------------------------------------------------- labels
def test_label_matches_analytic_torus():
    """A non-convex closed surface: the parity test agrees with the analytic inside test wherever
    the polygonised surface is not within a hair of the voxel centre."""
    R, r = 20.0, 7.0
    mesh = trimesh.creation.torus(R, r, major_sections=96, minor_sections=48)
    grid = centred_grid((24, 40, 40), 1.5)
    label = mv.mesh_to_label(mesh.vertices, mesh.faces, grid)
    p = grid.points()
    d = np.hypot(np.hypot(p[..., 0], p[..., 1]) - R, p[..., 2]) - r  # analytic SDF of the torus
    sure = np.abs(d) > 0.1  # polygonisation error of this mesh is < 0.05 mm
    assert np.array_equal(label[sure], (d < 0)[sure])
    assert label.sum() * 1.5**3 == pytest.approx(mesh.volume, rel=0.03)


def test_label_grid_aligned_box_counts_each_boundary_once():
    """Faces, edges and vertices lying exactly on voxel centres and columns: every boundary
    voxel is counted once (half-open box), never twice or with a broken parity."""
    box = trimesh.creation.box((10.0, 10.0, 10.0))
    grid = centred_grid((11, 11, 11), 2.0)  # centres at -10, -8, ..., 10: the faces at +-5 are not on them
    assert mv.mesh_to_label(box.vertices, box.faces, grid).sum() == 5**3
    grid = Grid((12, 12, 12), (-11.0, -11.0, -11.0), (2.0, 2.0, 2.0))  # centres at odd numbers: -5 and 5 on faces
    lab = mv.mesh_to_label(box.vertices, box.faces, grid)
    assert lab.sum() == 5**3  # of the 6 centre planes -5..5, one side is in, the other out
    k, j, i = np.nonzero(lab)
    assert (np.ptp(k), np.ptp(j), np.ptp(i)) == (4, 4, 4)  # a solid 5x5x5 block, no holes


def test_label_volume_of_rotated_ellipsoid_within_two_percent(rng):
    mesh = trimesh.creation.icosphere(4, radius=1.0)
    v = mesh.vertices * np.array([30.0, 18.0, 12.0]) @ rotation(rng).T + np.array([3.0, -2.0, 1.0])
    grid = centred_grid((36, 40, 40), 2.0)
    vol = mv.mesh_to_label(v, mesh.faces, grid).sum() * 8.0
    assert vol == pytest.approx(trimesh.Trimesh(v, mesh.faces).volume, rel=0.02)


def test_label_rejects_open_mesh():
    mesh = trimesh.creation.icosphere(2, radius=5.0)
    with pytest.raises(ValueError, match="not watertight"):
        mv.mesh_to_label(mesh.vertices, mesh.faces[:-3], centred_grid((8, 8, 8), 2.0))
    with pytest.raises(ValueError, match="vertices"):
        mv.mesh_to_label(np.zeros((3, 3)), mesh.faces, centred_grid((8, 8, 8), 2.0))


# --------------------------------------------------------------------------------------- distances
def test_signed_distance_sphere_sign_and_scale():
    R = 20.0
    mesh = trimesh.creation.icosphere(5, radius=R)
    grid = centred_grid((32, 32, 32), 2.0)
    true = np.linalg.norm(grid.points(), axis=-1) - R
    sdf = mv.signed_distance((mesh.vertices, mesh.faces), grid)
    assert sdf.dtype == np.float32
    assert np.all(np.sign(sdf[np.abs(true) > 0.05]) == np.sign(true[np.abs(true) > 0.05]))
    near = np.abs(true) < 2.0
    assert np.abs(sdf - true)[near].max() < 0.05  # exact triangle distance in the band (mesh error ~0.01)
    assert np.abs(sdf - true).max() < 0.6 * 2.0  # distance transform elsewhere: within ~half a voxel
    assert sdf.min() == pytest.approx(true.min(), abs=1.0)  # the deepest voxel is about R - sqrt(3) deep
    label_only = mv.signed_distance(true < 0, grid)
    assert np.abs(label_only - true).max() < 0.6 * 2.0
    assert np.all((label_only < 0) == (true < 0))


def test_point_mesh_distance_matches_brute_force(rng):
    mesh = trimesh.creation.icosphere(2, radius=10.0)
    v = mesh.vertices * np.array([1.0, 0.6, 1.4])
    pts = rng.uniform(-16, 16, size=(300, 3))
    got = mv.point_mesh_distance(pts, v, mesh.faces)
    # brute force: dense barycentric sampling of every triangle gives an upper bound close to the truth
    from scipy.spatial import cKDTree

    tri = v[mesh.faces]
    a, b = np.meshgrid(np.linspace(0, 1, 31), np.linspace(0, 1, 31))
    keep = a + b <= 1
    w = np.stack([1 - a[keep] - b[keep], a[keep], b[keep]], 1)
    samples = np.einsum("sk,fkc->fsc", w, tri).reshape(-1, 3)
    brute, _ = cKDTree(samples).query(pts)
    assert np.all(got <= brute + 1e-9)
    assert np.abs(got - brute).max() < 0.15  # sample spacing ~0.2 mm on these triangles
    # long slivers (a capsule's sides) do not fool the candidate search
    cap = trimesh.creation.capsule(height=100.0, radius=5.0, count=[24, 24])
    q = np.array([[5.5, 0.0, -45.0], [0.0, -7.0, 40.0], [0.0, 0.0, 60.0]])
    assert np.allclose(mv.point_mesh_distance(q, cap.vertices, cap.faces), [0.5 + 5 * (1 - np.cos(np.pi / 24)) * 0,
                       2.0, 5.0], atol=0.05)


def test_signed_distance_errors():
    grid = centred_grid((8, 8, 8), 1.0)
    with pytest.raises(ValueError, match="nothing is inside"):
        mv.signed_distance(np.zeros(grid.shape, bool), grid)
    with pytest.raises(ValueError, match="everything is inside"):
        mv.signed_distance(np.ones(grid.shape, bool), grid)
    with pytest.raises(ValueError, match="does not match"):
        mv.signed_distance(np.zeros((3, 3, 3), bool), grid)


# --------------------------------------------------------------------------------------- density
@pytest.fixture(scope="module")
def long_bone():
    """A capsule 'long bone' (radius 12 mm, 160 mm long, along z) in a slim limb, 1 mm grid.
    The surface comes from marching cubes of the analytic capsule (even ~1 mm triangles)."""
    from skimage.measure import marching_cubes

    z, y, x = np.mgrid[-84:84.1:1.0, -16:16.1:1.0, -16:16.1:1.0]
    d = np.sqrt(x**2 + y**2 + np.maximum(np.abs(z) - 68.0, 0.0) ** 2) - 12.0
    verts, faces, _, _ = marching_cubes(d, 0.0, spacing=(1.0, 1.0, 1.0), allow_degenerate=False)
    mesh = trimesh.Trimesh(verts[:, ::-1] - np.array([16.0, 16.0, 84.0]), faces[:, ::-1])
    assert mesh.is_watertight and mesh.volume > 0
    grid = centred_grid((168, 72, 72), 1.0)
    label = mv.mesh_to_label(mesh.vertices, mesh.faces, grid)
    sdf = mv.signed_distance((mesh.vertices, mesh.faces), grid)
    params = ph.DensityParams(soft_tissue=ph.SoftTissue(min_semi_axes_mm=(28.0, 26.0), margin_mm=8.0, fat_mm=5.0,
                                                        skin_mm=2.0))
    vol, tissue, frac = ph.density_volume(label, sdf, grid, params, seed=5, return_fractions=True)
    return mesh, grid, label, sdf, params, vol, tissue, frac


def test_density_values_in_their_stated_ranges(long_bone):
    _, _, _, _, params, vol, tissue, frac = long_bone
    ranges = params.ranges()
    for code, name in enumerate(ph.TISSUE_NAMES):
        pure = frac[code] > 0.999
        assert pure.sum() > 50, f"no pure {name} voxels"
        lo, hi = ranges[name]
        vals = vol[pure]
        assert vals.min() >= lo - 1e-6 and vals.max() <= hi + 1e-6, (name, vals.min(), vals.max())
    # the stated literature values (1/mm at 70 keV) and their order
    assert 0.045 <= params.cortical <= 0.06 and 0.025 <= params.trabecular <= 0.03
    assert 0.017 <= params.marrow <= 0.019 and 0.017 <= params.fat <= 0.019 and 0.020 <= params.muscle <= 0.021
    assert params.air == 0.0
    assert np.allclose(frac.sum(0), 1.0, atol=1e-5)
    assert vol.min() >= 0.0 and vol.max() <= params.cortical_range[1] + 1e-6


def test_density_structure_along_the_long_axis(long_bone):
    _, grid, label, _, params, vol, tissue, _ = long_bone
    nz = grid.shape[0]
    mid, end = nz // 2, nz // 2 - 62  # mid-shaft, and 62 mm down (t ~ 0.11: near the end)
    cy, cx = grid.shape[1] // 2, grid.shape[2] // 2
    # cortex thickness along a radius: about cortex_mid_mm at mid-shaft, about cortex_end_mm near the ends
    ray_mid = tissue[mid, cy, cx:]
    ray_end = tissue[end, cy, cx:]
    assert abs(np.sum(ray_mid == ph.CORTICAL) - params.cortex_mid_mm) <= 1.0
    assert abs(np.sum(ray_end == ph.CORTICAL) - params.cortex_end_mm) <= 1.0
    assert tissue[mid, cy, cx] == ph.MARROW  # medullary canal in the shaft
    assert tissue[end, cy, cx] == ph.TRABECULAR  # cancellous bone in the ends
    # soft tissue: muscle around the bone, then fat, then skin, then air
    ray = tissue[mid, cy, cx:]
    out = ray[np.argmax(ray == ph.MUSCLE):]
    order = [t for i, t in enumerate(out) if i == 0 or t != out[i - 1]]
    assert order == [ph.MUSCLE, ph.FAT, ph.SKIN, ph.AIR]
    assert np.all(vol[:, 0, :] == 0) and np.all(vol[:, :, 0] == 0)  # air at the sides


def test_density_is_deterministic_and_seeded(long_bone):
    _, grid, label, sdf, params, vol, _, _ = long_bone
    again, _ = ph.density_volume(label, sdf, grid, params, seed=5)
    assert np.array_equal(again, vol)
    other, _ = ph.density_volume(label, sdf, grid, params, seed=6)
    assert not np.array_equal(other, vol)
    assert np.array_equal(other[~label], vol[~label])  # only the bone's texture depends on the seed here


def test_subject_variation_is_seeded_and_bounded():
    base = ph.DensityParams()
    a, b = ph.vary_params(base, 11), ph.vary_params(base, 11)
    assert a == b
    many = [ph.vary_params(base, s) for s in range(200)]
    cortex = np.array([m.cortex_mid_mm for m in many]) / base.cortex_mid_mm
    assert 0.03 < cortex.std() < 0.2 and abs(cortex.mean() - 1) < 0.03
    for m in many:
        assert base.cortical_range[0] <= m.cortical <= base.cortical_range[1]
        assert base.trabecular_range[0] <= m.trabecular <= base.trabecular_range[1]
        assert m.soft_tissue.fat_mm > 0 and m.soft_tissue.margin_mm > 0


def test_make_phantom_rejects_a_surface_outside_the_grid():
    mesh = trimesh.creation.icosphere(2, radius=10.0)
    with pytest.raises(ValueError, match="does not fit"):
        ph.make_phantom(mesh.vertices + 100.0, mesh.faces, centred_grid((16, 16, 16), 2.0))


def test_make_phantom_same_seed_same_bits():
    mesh = trimesh.creation.icosphere(3, radius=1.0)
    mesh = trimesh.Trimesh(mesh.vertices * np.array([8.0, 7.0, 30.0]), mesh.faces)
    grid = centred_grid((40, 48, 48), 2.0)
    a = ph.make_phantom(mesh.vertices, mesh.faces, grid, seed=3)
    b = ph.make_phantom(mesh.vertices, mesh.faces, grid, seed=3)
    c = ph.make_phantom(mesh.vertices, mesh.faces, grid, seed=4)
    assert a.volume.dtype == np.float32 and a.volume.shape == grid.shape
    assert np.array_equal(a.volume, b.volume) and a.params == b.params
    assert not np.array_equal(a.volume, c.volume)
    assert np.all(np.isfinite(a.volume))


# --------------------------------------------------------------------------------------- alignment
def test_align_rigid_recovers_pose_and_mirror(rng):
    mesh = trimesh.creation.icosphere(3, radius=1.0)
    ref = mesh.vertices * np.array([40.0, 15.0, 8.0])
    ref = ref + 6.0 * np.maximum(ref[:, [0]], 0) ** 2 / 40.0 * np.array([0.0, 1.0, 0.5])  # break symmetries
    R = rotation(rng)
    t = np.array([120.0, -40.0, 900.0])
    moved = ref @ R.T + t
    al = align_rigid(moved, ref)
    assert not al.mirrored and al.rms_mm < 0.05
    assert np.abs(al.apply(moved) - ref).max() < 0.05
    mirrored = (ref * np.array([-1.0, 1.0, 1.0])) @ R.T + t  # the other side's bone ...
    mirrored_faces = mesh.faces[:, ::-1]  # ... with its outward normals
    al = align_rigid(mirrored, ref)
    assert al.mirrored and al.rms_mm < 0.05
    assert np.abs(al.apply(mirrored) - ref).max() < 0.05
    v, f = al.apply_mesh(mirrored, mirrored_faces)
    assert trimesh.Trimesh(v, f, process=False).volume > 0  # winding restored: outward normals


def test_load_mesh_formats(tmp_path):
    """The loader the phantom's mesh import uses gives closed meshes back (STL corners merged)."""
    from clgs.io.mesh import MeshError, check_mesh, load_mesh

    mesh = trimesh.creation.icosphere(2, radius=7.0)
    mesh.export(tmp_path / "m.stl")
    np.savez(tmp_path / "m.npz", vertices=mesh.vertices, faces=mesh.faces)
    for name in ("m.stl", "m.npz"):
        v, f = load_mesh(tmp_path / name, space="RAS")  # trimesh's file: no frame tag
        check_mesh(v, f, closed=True)  # watertight
        assert abs(mv.mesh_volume(v, f) - mesh.volume) < 1e-3 * mesh.volume
    with pytest.raises(MeshError, match="no such file"):
        load_mesh(tmp_path / "missing.stl")
    np.savez(tmp_path / "bad.npz", points=mesh.vertices)
    with pytest.raises(ValueError, match="vertices"):
        load_mesh(tmp_path / "bad.npz")


def test_scan_geometry_sees_the_whole_volume():
    from clgs.geometry import Geometry

    grid = centred_grid((160, 72, 80), 3.0)
    kw = scan_geometry_kwargs(grid)
    geo = Geometry.from_dict(dict(kw, angles=np.linspace(0, np.pi, 8, endpoint=False)))
    nz, ny, nx = grid.shape
    corners = np.array([[sx * nx * 1.5, sy * ny * 1.5, sz * nz * 1.5] for sx in (-1, 1) for sy in (-1, 1)
                        for sz in (-1, 1)])
    for view in range(geo.n_views):
        vec = geo.view_vectors(scene=False, views=[view])[0]
        src, det, eu, ev = vec[0:3], vec[3:6], vec[6:9], vec[9:12]
        n = np.cross(eu, ev)
        for c in corners:  # project each corner of the volume onto the detector plane
            d = c - src
            s = np.dot(det - src, n) / np.dot(d, n)
            hit = src + s * d - det
            u = np.dot(hit, eu) / np.dot(eu, eu)
            v = np.dot(hit, ev) / np.dot(ev, ev)
            assert abs(u) <= (geo.nDetector[1] - 1) / 2 and abs(v) <= (geo.nDetector[0] - 1) / 2
