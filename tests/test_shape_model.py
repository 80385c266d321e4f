"""Shape model of stationary velocity fields: exp by scaling and squaring, sampling, files."""
import json

import numpy as np
import pytest
import torch
from scipy.ndimage import map_coordinates

from clgs.shape.model import (
    MIN_SQUARINGS,
    DensityAtlas,
    ModelFileError,
    ShapeModel,
    exp_velocity,
    jacobian_determinant,
    load_model,
    read_metadata,
    sample_field,
    save_model,
    squarings_for,
)
from clgs.shape.template import grid_points

SHAPE, SP, ORG = (20, 22, 24), (2.0, 2.0, 2.0), (-19.0, -21.0, -23.0)
SMALL = (12, 13, 14)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _points():
    return torch.as_tensor(grid_points(SHAPE, SP, ORG))  # float64 (Z, Y, X, 3)


def _smooth_field(P, amplitude=1.0):
    x, y, z = P[..., 0], P[..., 1], P[..., 2]
    return amplitude * torch.stack([6 * torch.sin(y / 10) * torch.cos(z / 12), 5 * torch.cos(x / 9),
                                    4 * torch.sin(x / 11 + y / 13)], 0)


def _rk4_flow(v, pts, n=64):
    f = lambda p: sample_field(v, p, SP, ORG)  # noqa: E731
    h = 1.0 / n
    for _ in range(n):
        k1 = f(pts)
        k2 = f(pts + h / 2 * k1)
        k3 = f(pts + h / 2 * k2)
        k4 = f(pts + h * k3)
        pts = pts + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return pts


def test_scaling_and_squaring_matches_runge_kutta():
    P = _points()
    v = _smooth_field(P)
    u = exp_velocity(v, SP)
    flat = P.reshape(-1, 3)
    u_rk = (_rk4_flow(v, flat.clone()) - flat).T.reshape(3, *SHAPE)
    err = (u - u_rk).norm(dim=0) / SP[0]  # in cells
    assert float(u.norm(dim=0).max()) > 3.0 * SP[0]  # a real deformation (over 3 cells)
    assert float(err.max()) < 0.15
    assert float(err.mean()) < 0.05


def test_exp_v_composed_with_exp_minus_v_is_identity():
    P = _points()
    v = _smooth_field(P)
    u, ui = exp_velocity(v, SP), exp_velocity(-v, SP)
    flat = P.reshape(-1, 3)
    comp = ui + sample_field(u, flat + ui.reshape(3, -1).T, SP, ORG).T.reshape(3, *SHAPE)
    inner = comp.norm(dim=0)[4:-4, 4:-4, 4:-4] / SP[0]
    assert float(inner.max()) < 0.25
    assert float(inner.mean()) < 0.1


def test_stiff_rotation_is_fold_free_and_exact():
    """A rotation of 2 rad about z: velocities of 23 cells at the corners."""
    P = _points()
    w = 2.0
    v = torch.stack([-w * P[..., 1], w * P[..., 0], torch.zeros_like(P[..., 0])], 0)
    assert float(v.abs().max()) / SP[0] > 20
    n = squarings_for(v, SP)
    assert n >= 6
    u = exp_velocity(v, SP)
    assert torch.isfinite(u).all()
    det = jacobian_determinant(u, SP)
    assert det.min() > 0
    c, s = np.cos(w), np.sin(w)
    R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]], dtype=torch.float64)
    flat = P.reshape(-1, 3)
    u_true = (flat @ R.T - flat).T.reshape(3, *SHAPE)
    inside = P[..., :2].norm(dim=-1) < 12  # away from the clamped border
    assert float((u - u_true).norm(dim=0)[inside].max()) < 0.25 * SP[0]
    assert abs(det[inside.numpy()] - 1).max() < 0.1  # rotations keep volume


def test_squarings_rule():
    v = torch.zeros(3, 4, 5, 6)
    assert squarings_for(v, (1, 1, 1)) == MIN_SQUARINGS
    for cells in (3.0, 16.0, 100.0):
        v[0, 1, 2, 3] = cells
        n = squarings_for(v, (1.0, 1.0, 1.0), min_squarings=0)
        assert cells / 2 ** n < 0.5 <= cells / 2 ** (n - 1)
    v[0, 1, 2, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        squarings_for(v, (1, 1, 1))


def test_sampling_matches_scipy_and_clamps_outside(rng):
    field = torch.as_tensor(rng.standard_normal((2,) + SHAPE))
    lo, hi = np.asarray(ORG[::-1]), np.asarray(ORG[::-1]) + (np.asarray(SHAPE[::-1]) - 1) * 2.0
    pts = lo + (hi - lo) * rng.random((300, 3))
    got = sample_field(field, torch.as_tensor(pts), SP, ORG).numpy()
    idx = ((pts[:, ::-1] - np.asarray(ORG)) / 2.0).T
    ref = np.stack([map_coordinates(field[c].numpy(), idx, order=1) for c in range(2)], 1)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10)
    # beyond the box: the value at the nearest border point
    far = torch.as_tensor([[lo[0] - 50.0, lo[1] + 4.0, lo[2] + 6.0]])
    border = torch.as_tensor([[lo[0], lo[1] + 4.0, lo[2] + 6.0]])
    np.testing.assert_allclose(sample_field(field, far, SP, ORG), sample_field(field, border, SP, ORG))


def test_jacobian_of_affine_map():
    P = _points()
    A = torch.tensor([[0.1, 0.05, 0.0], [-0.02, 0.2, 0.03], [0.0, 0.01, -0.1]], dtype=torch.float64)
    u = (P.reshape(-1, 3) @ A.T).T.reshape(3, *SHAPE)
    det = jacobian_determinant(u, SP)
    np.testing.assert_allclose(det, np.linalg.det(np.eye(3) + A.numpy()), rtol=1e-5)


def _model(rng, n_subjects=12, dtype=torch.float32, shape=SMALL):
    """A PCA model of smooth random velocity fields (about 1.5 cells at one sigma)."""
    P = torch.as_tensor(grid_points(shape, SP, ORG))
    fields = []
    for _ in range(n_subjects):
        k = rng.uniform(0.05, 0.15, size=(3, 3))
        ph = rng.uniform(0, 6.3, size=(3,))
        amp = rng.normal(0, 3.0, size=(3,))
        fields.append(torch.stack([amp[c] * torch.sin(P @ torch.as_tensor(k[c]) + ph[c]) for c in range(3)], 0))
    X = torch.stack(fields).reshape(n_subjects, -1)
    mean = X.mean(0)
    _, s, vt = torch.linalg.svd(X - mean, full_matrices=False)
    m = 5
    return ShapeModel(mean.reshape(3, *shape), vt[:m].reshape(m, 3, *shape), s[:m] / np.sqrt(n_subjects - 1),
                      SP, ORG, dtype=dtype), X


def test_jacobian_positive_within_three_sigma(rng):
    model, _ = _model(rng)
    trials = [3.0 * np.eye(model.n_modes)[i] * sign for i in range(model.n_modes) for sign in (1, -1)]
    trials += [np.clip(rng.standard_normal(model.n_modes), -3, 3) for _ in range(4)]
    biggest = 0.0
    for alpha in trials:
        u = model.displacement(torch.as_tensor(alpha, dtype=torch.float32))
        biggest = max(biggest, float(u.norm(dim=0).max()))
        assert model.jacobian_determinant(u=u).min() > 0
    assert biggest > 1.0 * SP[0]  # the test deforms for real


def test_velocity_is_linear_in_alpha_and_projection_inverts_it(rng):
    model, _ = _model(rng, dtype=torch.float64)
    alpha = torch.as_tensor(rng.standard_normal(model.n_modes))
    v = model.velocity(alpha)
    manual = model.mean + sum(alpha[m] * model.sigma[m] * model.modes[m] for m in range(model.n_modes))
    torch.testing.assert_close(v, manual)
    torch.testing.assert_close(model.project(v), alpha)
    with pytest.raises(ValueError, match="entries"):
        model.velocity(torch.zeros(model.n_modes + 1))


def test_gradcheck_deformation_wrt_alpha(rng):
    small = (7, 8, 9)
    model, _ = _model(rng, n_subjects=6, dtype=torch.float64, shape=small)
    model = ShapeModel(model.mean, model.modes[:3], model.sigma[:3], SP, ORG, dtype=torch.float64)
    pts = torch.as_tensor(grid_points(small, SP, ORG).reshape(-1, 3)[rng.choice(7 * 8 * 9, 12, replace=False)])
    pts = pts + torch.as_tensor(rng.uniform(0.2, 0.8, (12, 3)))  # off the grid nodes
    n = squarings_for(model.velocity(torch.full((3,), 1.0, dtype=torch.float64)), SP) + 1

    def f(alpha):
        u = exp_velocity(model.velocity(alpha), SP, n_squarings=n)
        return pts + model.sample(u, pts)

    alpha = torch.as_tensor(rng.standard_normal(3) * 0.5, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(f, (alpha,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_save_load_roundtrip_and_metadata(tmp_path, rng):
    model, _ = _model(rng)
    mean = rng.random((6, 7, 8)).astype(np.float32)
    atlas = DensityAtlas(mean, 0.1 * mean, (3.0, 3.0, 3.0), (1.0, 2.0, 3.0))
    path = tmp_path / "m.npz"
    save_model(path, model, atlas, {"population": ["a", "b"], "variance_kept": 0.95})
    meta = read_metadata(path)
    assert meta["format"] == "clgs.shape_model" and meta["version"] == 1
    assert meta["population"] == ["a", "b"] and meta["n_modes"] == model.n_modes
    sm, at = load_model(path)
    torch.testing.assert_close(sm.modes, model.modes)
    torch.testing.assert_close(sm.sigma, model.sigma)
    assert sm.spacing == SP and sm.origin == ORG
    np.testing.assert_array_equal(at.mean, mean)
    assert at.spacing == (3.0, 3.0, 3.0) and at.origin == (1.0, 2.0, 3.0)
    with np.load(path, allow_pickle=False) as z:  # plain arrays only
        assert all(z[k].dtype != object for k in z.files)
    assert ShapeModel.load(path).n_modes == model.n_modes
    assert DensityAtlas.load(path).shape == (6, 7, 8)


def test_load_rejects_bad_files(tmp_path, rng):
    model, _ = _model(rng)
    good = tmp_path / "good.npz"
    save_model(good, model)
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["metadata"]).decode())

    def write(name, **changes):
        a = dict(arrays)
        m = dict(meta)
        m.update(changes.pop("meta", {}))
        a["metadata"] = np.frombuffer(json.dumps(m).encode(), np.uint8)
        a.update(changes)
        np.savez(tmp_path / name, **a)
        return tmp_path / name

    with pytest.raises(ModelFileError, match="upgrade clgs"):
        load_model(write("future.npz", meta={"version": 99}))
    with pytest.raises(ModelFileError, match="not a clgs shape model"):
        load_model(write("other.npz", meta={"format": "something"}))
    with pytest.raises(ModelFileError, match="sigma"):
        load_model(write("sigma.npz", sigma=np.ones(2, np.float32)))
    with pytest.raises(ModelFileError, match="modes must be"):
        load_model(write("modes.npz", modes=arrays["modes"][:, :, :-1]))
    with pytest.raises(ModelFileError, match="does not exist"):
        load_model(tmp_path / "missing.npz")
    with pytest.raises(ModelFileError, match="no density atlas"):
        DensityAtlas.load(good)
    np.save(tmp_path / "plain.npy", np.zeros(3))
    with pytest.raises(ModelFileError):
        load_model(tmp_path / "plain.npy")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ModelFileError, match="cannot read model file.*rebuild it"):
        read_metadata(truncated)
    objects = tmp_path / "objects.npz"
    np.savez(objects, **{**arrays, "sigma": np.array([{"a": 1}, None], dtype=object)})
    with pytest.raises(ModelFileError, match="cannot read model file"):
        load_model(objects)
    mean = rng.random((6, 7, 8)).astype(np.float32)
    with_atlas = tmp_path / "atlas.npz"
    save_model(with_atlas, model, DensityAtlas(mean, 0.1 * mean, (3.0, 3.0, 3.0), (1.0, 2.0, 3.0)))
    with np.load(with_atlas, allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    m = json.loads(bytes(a["metadata"]).decode())
    m["atlas_shape"] = [6, 7, 9]
    a["metadata"] = np.frombuffer(json.dumps(m).encode(), np.uint8)
    np.savez(tmp_path / "atlas_meta.npz", **a)
    with pytest.raises(ModelFileError, match="atlas arrays do not match the metadata"):
        load_model(tmp_path / "atlas_meta.npz")


def test_density_atlas_sampling(rng):
    mean = rng.random((5, 6, 7)).astype(np.float32)
    atlas = DensityAtlas(mean, mean ** 2, (2.0, 2.0, 2.0), (10.0, 0.0, -4.0))
    nodes = grid_points(atlas.shape, atlas.spacing, atlas.origin).reshape(-1, 3)
    np.testing.assert_allclose(atlas.mean_at(nodes), mean.reshape(-1), rtol=1e-6)
    np.testing.assert_allclose(atlas.var_at(nodes), (mean ** 2).reshape(-1), rtol=1e-6)
    assert atlas.mean_at(np.array([[1000.0, 0, 0]]))[0] == 0.0  # air outside
    mid = 0.5 * (nodes[0] + nodes[1])  # halfway along x
    assert atlas.mean_at(mid[None])[0] == pytest.approx(0.5 * (mean[0, 0, 0] + mean[0, 0, 1]), rel=1e-5)
    p = torch.as_tensor(nodes[50:60] + 0.3).requires_grad_(True)
    atlas.sample(p).sum().backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    with pytest.raises(ModelFileError):
        DensityAtlas(mean, -mean, (1, 1, 1), (0, 0, 0))


def test_anatomies_lists_an_unreadable_model_as_such(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from click.testing import CliRunner

    from clgs.anatomy import plugins
    from clgs.cli.anatomies import anatomies

    bad = tmp_path / "model.npz"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    fake = SimpleNamespace(summary="a bone", version="1", package="pkg", model_path=str(bad))
    monkeypatch.setattr(plugins, "anatomies", lambda: {"bone": fake})
    out = CliRunner().invoke(anatomies, []).output
    assert "model (unreadable)" in out and "rebuild it" in out
    assert '"built": false' in CliRunner().invoke(anatomies, ["--json"]).output


def test_density_atlas_mean_and_var_in_one_pass_give_the_same_bits(rng):
    mean = rng.random((5, 6, 7)).astype(np.float32)
    atlas = DensityAtlas(mean, 0.3 * mean ** 2, (2.0, 2.0, 2.0), (10.0, 0.0, -4.0))
    lo = np.array([-4.0, 0.0, 10.0]) - 3.0  # (x, y, z): some points outside the grid
    pts = torch.as_tensor(lo + rng.random((3000, 3)) * (np.array([12.0, 10.0, 8.0]) + 6.0))
    for dt in (torch.float64, torch.float32):
        m, v = atlas.mean_var_at(pts.to(dt))
        assert torch.equal(m, atlas.mean_at(pts.to(dt))) and torch.equal(v, atlas.var_at(pts.to(dt)))
        assert (m == 0).any() and (m > 0).any()
