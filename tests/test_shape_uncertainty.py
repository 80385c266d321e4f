"""The shape surface's uncertainty field (clgs.shape.uncertainty): the analytic answer of a model
of known covariance, the Laplace covariance of a linear-Gaussian problem, the files read back by
trimesh and meshio, and a shape-guided run that writes them and reports their summary."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from clgs.anatomy import AnatomyParts

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _translation_model(steps_mm=(2.0, 3.0)):
    """Two modes that translate everything: along x by steps_mm[0] and along z by steps_mm[1]
    per standard deviation (exp of a constant velocity field is exactly that translation)."""
    from clgs.shape.model import ShapeModel

    shape, spacing, origin = (6, 6, 6), (4.0, 4.0, 4.0), (-10.0, -10.0, -10.0)
    modes = np.zeros((2, 3) + shape, np.float32)
    modes[0, 0] = 1.0
    modes[1, 2] = 1.0
    norm = np.sqrt(np.prod(shape))
    modes /= norm
    sigma = np.array(steps_mm, np.float32) * norm
    return ShapeModel(np.zeros((3,) + shape, np.float32), modes, sigma, spacing, origin)


def test_the_field_is_sqrt_of_n_gcg_n_for_a_model_of_known_covariance():
    import trimesh

    from clgs.shape.uncertainty import map_jacobian, normal_sd

    model = _translation_model((2.0, 3.0))
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=6.0)
    v = torch.as_tensor(sphere.vertices, dtype=torch.float32)

    def moved(a):
        with torch.no_grad():
            u = model.displacement(torch.as_tensor(a, dtype=torch.float32))
            return (v + model.sample(u, v)).numpy()

    G = map_jacobian(moved, np.zeros(2))
    np.testing.assert_allclose(G[:, 0, 0], 2.0, rtol=1e-4)  # mode 1 moves x by 2 mm per unit
    np.testing.assert_allclose(G[:, 2, 1], 3.0, rtol=1e-4)
    C = np.array([[0.5, 0.2], [0.2, 0.8]])
    n = sphere.vertex_normals
    got = normal_sd(G, n, C)
    # analytic: the normal moves by 2 n_x a_1 + 3 n_z a_2, whose variance is g^T C g
    gx, gz = 2.0 * n[:, 0], 3.0 * n[:, 2]
    want = np.sqrt(C[0, 0] * gx ** 2 + 2 * C[0, 1] * gx * gz + C[1, 1] * gz ** 2)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
    # the prior alone (C = I): sqrt(4 n_x^2 + 9 n_z^2): largest at the poles of z, 0 around y's
    prior = normal_sd(G, n, np.eye(2))
    assert prior.max() == pytest.approx(3.0, rel=1e-3) and prior.min() < 0.05


def test_beyond_the_span_covariance_is_the_leave_one_out_residuals_and_gives_sqrt_n_s_n(tmp_path):
    import trimesh

    from clgs.shape.builder import beyond_span_covariance
    from clgs.shape.model import load_model, save_model
    from clgs.shape.uncertainty import beyond_sd

    rng = np.random.default_rng(2)
    shape = (4, 5, 6)
    n, d = 7, 3 * 4 * 5 * 6
    V = rng.normal(size=(n, 2)) @ rng.normal(size=(2, d)) * 3 + rng.normal(size=(n, d)) * 0.5
    cov = beyond_span_covariance(V, 1, shape)
    # one grid point (z=1, y=2, x=3) by hand: the left-out residuals of a 1-mode PCA
    idx = [np.ravel_multi_index((c, 1, 2, 3), (3,) + shape) for c in range(3)]
    r = []
    for i in range(n):
        rest = np.delete(V, i, 0)
        m = rest.mean(0)
        u = np.linalg.svd(rest - m)[2][0]
        r.append(((V[i] - m) - ((V[i] - m) @ u) * u)[idx])
    r = np.array(r)
    want = r.T @ r / n
    got = cov[:, 1, 2, 3]
    np.testing.assert_allclose(got[[0, 1, 2, 3, 4, 5]], want[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]], rtol=1e-5)
    # a model carrying a known constant covariance: the field is sqrt(n^T S n) anywhere
    model = _translation_model()
    S = np.array([[4.0, 1.0, 0.5], [1.0, 1.0, 0.0], [0.5, 0.0, 9.0]])
    const = np.stack([np.full(model.shape, x, np.float32) for x in S[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]])
    model.beyond_cov = const
    save_model(tmp_path / "m.npz", model)
    model = load_model(tmp_path / "m.npz")[0]  # kept in the file
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=5.0)
    nrm = sphere.vertex_normals
    np.testing.assert_allclose(beyond_sd(model, sphere.vertices, nrm, size=1.5),
                               1.5 * np.sqrt(np.einsum("vi,ij,vj->v", nrm, S, nrm)), rtol=1e-5)


def test_laplace_covariance_of_a_linear_gaussian_problem():
    from clgs.errors import InputError
    from clgs.shape.uncertainty import laplace_covariance

    rng = np.random.default_rng(0)
    P, M, noise = 4000, 3, 0.2
    J = rng.normal(size=(P, M)) * [0.02, 0.005, 0.001]
    a_true = rng.normal(size=M)
    y = J @ a_true + rng.normal(size=P) * noise
    # the MAP of the linear-Gaussian problem with prior N(0, I) and the true noise
    H = J.T @ J / noise ** 2 + np.eye(M)
    a_map = np.linalg.solve(H, J.T @ y / noise ** 2)
    C, s2 = laplace_covariance(J, J @ a_map - y)
    assert np.sqrt(s2) == pytest.approx(noise, rel=0.05)
    np.testing.assert_allclose(C, np.linalg.inv(H), rtol=0.1, atol=1e-6)
    # a mode the data do not see keeps the prior's spread; one they see well is narrowed
    assert C[2, 2] > 0.9 and C[0, 0] < 0.2
    with pytest.raises(InputError, match="NaN"):
        laplace_covariance(J, np.full(P, np.nan))


def test_the_files_open_in_trimesh_and_meshio_with_the_values(tmp_path):
    import meshio
    import trimesh

    from clgs.shape.uncertainty import FIELD, read_uncertainty_ply, write_uncertainty_files

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=6.0)
    v = sphere.vertices + [10.0, -20.0, 30.0]
    values = np.linspace(0.1, 2.0, len(v))
    paths = write_uncertainty_files(tmp_path, v, sphere.faces, values)
    got_v, got_f, got = read_uncertainty_ply(paths["ply"])
    np.testing.assert_allclose(got, values, rtol=1e-6)
    np.testing.assert_allclose(got_v, v, atol=1e-4)  # back in clgs's frame (the file is LPS, tagged)
    assert np.array_equal(got_f, sphere.faces)
    raw = trimesh.load(paths["ply"], process=False)  # trimesh on its own
    np.testing.assert_allclose(raw.metadata["_ply_raw"]["vertex"]["data"][FIELD].reshape(-1), values, rtol=1e-6)
    np.testing.assert_allclose(raw.vertices, v * [-1, -1, 1], atol=1e-4)
    m = meshio.read(paths["ply"])  # an independent PLY reader
    np.testing.assert_allclose(np.asarray(m.point_data[FIELD]).reshape(-1), values, rtol=1e-5)
    np.testing.assert_allclose(m.points, v * [-1, -1, 1], atol=1e-4)
    # the legacy VTK polydata, section by section (meshio reads no POLYDATA; VTK's own reader below)
    text = Path(paths["vtk"]).read_text().split("\n")
    assert text[0] == "# vtk DataFile Version 3.0" and "SPACE=LPS" in text[1] and text[3] == "DATASET POLYDATA"
    n = len(v)
    assert text[4] == f"POINTS {n} float"
    np.testing.assert_allclose(np.loadtxt(text[5:5 + n]), v * [-1, -1, 1], atol=1e-5)
    k = 5 + n
    assert text[k] == f"POLYGONS {len(sphere.faces)} {4 * len(sphere.faces)}"
    np.testing.assert_array_equal(np.loadtxt(text[k + 1:k + 1 + len(sphere.faces)], dtype=int)[:, 1:], sphere.faces)
    k += 1 + len(sphere.faces)
    assert text[k:k + 3] == [f"POINT_DATA {n}", f"SCALARS {FIELD} float 1", "LOOKUP_TABLE default"]
    np.testing.assert_allclose(np.loadtxt(text[k + 3:k + 3 + n]), values, atol=1e-6)


def test_vtks_own_reader_takes_the_legacy_file(tmp_path):
    vtk = pytest.importorskip("vtk")
    import trimesh
    from vtk.util.numpy_support import vtk_to_numpy

    from clgs.shape.uncertainty import FIELD, write_uncertainty_files

    sphere = trimesh.creation.icosphere(subdivisions=1, radius=6.0)
    values = np.linspace(0.1, 2.0, len(sphere.vertices))
    reader = vtk.vtkPolyDataReader()
    reader.SetFileName(str(write_uncertainty_files(tmp_path, sphere.vertices, sphere.faces, values)["vtk"]))
    reader.Update()
    poly = reader.GetOutput()
    assert poly.GetNumberOfPolys() == len(sphere.faces)
    np.testing.assert_allclose(vtk_to_numpy(poly.GetPointData().GetArray(FIELD)), values, rtol=1e-6)


def test_a_shape_guided_run_writes_the_field_and_reports_it(tmp_path):
    pytest.importorskip("clgs.ops.ct_projector")
    from test_shape_guided import _scan, _small, atlas, shape_model, template  # noqa: F401

    from clgs.methods.shape_guided import reconstruct_shape_guided
    from clgs.shape.uncertainty import read_uncertainty_ply

    t = template.__wrapped__()
    sm = shape_model.__wrapped__(t)
    at = atlas.__wrapped__(t)
    scan = _scan(t, n_views=2, shape_model=sm)
    res = reconstruct_shape_guided(scan, AnatomyParts(t, sm, at), iterations=20, out_dir=tmp_path / "run",
                                   **_small(alpha_freeze=3))
    u = res.uncertainty
    assert u is not None and u["file"] == "shape_uncertainty.ply" and 0 < u["mean_mm"] <= u["max_mm"]
    assert u["beyond_model_max_mm"] == 0.0  # a model without a beyond-span covariance: no such part
    assert u["mean_mm"] >= u["posterior_mean_mm"] and u["mean_mm"] >= u["volume_mean_mm"] > 0.0
    assert 0.0 <= u["share_above_2mm"] <= 1.0
    assert json.loads((tmp_path / "run" / "alpha.json").read_text())["uncertainty"] == u
    assert len(u["alpha_sd"]) == 2 and all(0 < s <= 1.0 + 1e-9 for s in u["alpha_sd"])  # narrower than the prior
    v, f, values = read_uncertainty_ply(tmp_path / "run" / "shape_uncertainty.ply")
    from clgs.io.mesh import load_mesh

    surface = load_mesh(tmp_path / "run" / "shape_surface.stl")
    assert len(v) == len(t.vertices) and np.isfinite(values).all()
    assert values.mean() == pytest.approx(u["mean_mm"], abs=1e-3)
    # the same surface as shape_surface.stl
    from scipy.spatial import cKDTree

    assert cKDTree(surface.vertices).query(v)[0].max() < 1e-3
    json.dumps(u)
    # the parts as written, read by trimesh alone: the field is the larger of the model's (the root
    # sum of squares of its two parts) and the volume's, each vertex's distance to surface.stl (the
    # bone surface the run wrote)
    import trimesh

    raw = trimesh.load(str(tmp_path / "run" / "shape_uncertainty.ply"), process=False).metadata["_ply_raw"]
    props = raw["vertex"]["data"]
    parts = {k: np.asarray(props[k], np.float64) for k in ("uncertainty_mm", "posterior_mm", "beyond_model_mm",
                                                            "volume_mm")}
    model = np.sqrt(parts["posterior_mm"] ** 2 + parts["beyond_model_mm"] ** 2)
    np.testing.assert_allclose(parts["uncertainty_mm"], np.maximum(model, parts["volume_mm"]), rtol=1e-5, atol=1e-6)
    assert (parts["volume_mm"] > model).any() and (parts["volume_mm"] < model).any()  # both parts matter here
    bone = load_mesh(tmp_path / "run" / "surface.stl")
    _, d, _ = trimesh.proximity.closest_point(trimesh.Trimesh(bone.vertices, bone.faces, process=False), v)
    np.testing.assert_allclose(parts["volume_mm"], d, atol=1e-3)
    # one view (along x) cannot see the shift along x: that mode keeps most of the prior's spread,
    # where two views pin it down
    one = reconstruct_shape_guided(_scan(t, n_views=1, shape_model=sm), AnatomyParts(t, sm, at), iterations=20,
                                   out_dir=tmp_path / "one", **_small(alpha_freeze=3)).uncertainty
    assert one["alpha_sd"][1] > 0.5 > 5 * u["alpha_sd"][1] and one["posterior_mean_mm"] > 5 * u["posterior_mean_mm"]


def test_the_share_above_2_mm_is_a_share_of_the_surfaces_area():
    """Two triangles, of 1 and 3 mm^2: the first's vertices above 2 mm make a quarter of the area,
    though half of the vertices."""
    from clgs.shape.uncertainty import area_share_above

    v = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 2, 0]], np.float64)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    values = np.array([3.0, 3.0, 3.0, 0.5, 0.5, 0.5])
    assert area_share_above(v, f, values, 2.0) == pytest.approx(0.25)
    assert area_share_above(v, f, values, 5.0) == 0.0 and area_share_above(v, f, values, 0.1) == pytest.approx(1.0)
