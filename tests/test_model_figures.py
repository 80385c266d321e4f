"""A model's figures (compactness, generalisation, specificity) and its mode count, decided from
them: the Gram-matrix leave-one-out against a direct SVD, the rule on known figures, and a build
that stores them (JSON in the metadata record), prints them, and an ``info`` that reads them."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _brute_force(x, measure, k):
    """Leave-one-out generalisation by a full-space SVD per subject, then measured: the definition."""
    n = len(x)
    out = np.zeros(k)
    for i in range(n):
        rest = np.delete(x, i, 0)
        m = rest.mean(0)
        vt = np.linalg.svd(rest - m, full_matrices=False)[2]
        for j in range(1, k + 1):
            recon = m + (x[i] - m) @ vt[:j].T @ vt[:j]
            d = measure((x[i] - recon)[None])[0].reshape(-1, 3)
            out[j - 1] += np.linalg.norm(d, axis=1).mean() / n
    return out


def test_field_figures_measured_through_a_linear_map_match_a_direct_leave_one_out():
    from clgs.shape.statistics import field_space_figures

    rng = np.random.default_rng(3)
    n, d = 9, 60
    x = (rng.normal(size=(n, 4)) * [8.0, 4.0, 1.0, 0.2]) @ np.linalg.qr(rng.normal(size=(d, 4)))[0].T + 100.0
    x += rng.normal(size=x.shape) * 0.01  # every mode carries something
    A = rng.normal(size=(d, 24)) / 5  # 8 points' worth of a linear "surface sampling"
    measure = lambda rows: np.asarray(rows) @ A  # noqa: E731
    f = field_space_figures(x, measure, max_modes=5, n_samples=20)
    np.testing.assert_allclose(f["generalisation_mm"], _brute_force(x, measure, 5), rtol=1e-9, atol=1e-10)
    s = np.linalg.svd(x - x.mean(0), compute_uv=False)
    np.testing.assert_allclose(f["compactness"], (np.cumsum(s ** 2) / np.sum(s ** 2))[:5], rtol=1e-10)
    assert json.loads(json.dumps(f)) == f  # plain JSON
    with pytest.raises(ValueError, match="P\\*3"):
        field_space_figures(x, lambda rows: np.asarray(rows)[:, :5])


def test_the_mode_rule_on_known_figures():
    from clgs.errors import InputError
    from clgs.shape.modes import choose_modes

    fig = {"compactness_all": [0.6, 0.85, 0.93, 0.97, 0.99, 1.0],
           "generalisation_mm": [3.0, 2.0, 1.5, 1.45, 1.44]}
    # 95 % needs 4 modes; past 3 the next mode gains 0.05 mm < 0.1: 3
    c = choose_modes(fig, 6, 0.95, 0.1)
    assert c["n_modes"] == 3 and "0.050 mm" in c["reason"]
    assert choose_modes(fig, 6, 0.95, 0.0)["n_modes"] == 4  # the variance rule alone
    assert choose_modes(fig, 6, 0.95, None)["n_modes"] == 4
    assert choose_modes(fig, 6, 0.80, 0.1)["n_modes"] == 2  # variance first
    assert choose_modes(fig, 6, 0.95, 0.6)["n_modes"] == 2  # 2 -> 3 gains 0.5 < 0.6
    assert choose_modes(fig, 6, n_modes=5)["n_modes"] == 5 and "asked" in choose_modes(fig, 6, n_modes=5)["reason"]
    too_many = choose_modes(fig, 6, n_modes=50)
    assert too_many["n_modes"] == 6 and "50 were asked (--n-modes), the population's PCA has 6" in too_many["reason"]
    assert choose_modes(None, 0)["n_modes"] == 0
    with pytest.raises(InputError, match="variance"):
        choose_modes(fig, 6, 1.5)
    with pytest.raises(InputError, match="tolerance"):
        choose_modes(fig, 6, 0.95, -1.0)


def _blob_anatomy(tmp_path, axes):
    from clgs.anatomy.record import Anatomy
    from clgs.shape.template import Subject, Template, box_grid, grid_points, mesh_from_sdf

    def blob(a, sid):
        a = np.asarray(a, float)
        shape, sp, org = box_grid(-a - 3, a + 3, spacing=1.5)
        v, f = mesh_from_sdf((np.linalg.norm(grid_points(shape, sp, org) / a, axis=-1) - 1) * a.min(), sp, org)
        return Subject(sid, v, f)

    mean = blob(np.mean(list(axes.values()), 0), "template")
    template = Template.from_mesh(mean.vertices, mean.faces, spacing=2.5, margin=8.0, name="blob")
    return Anatomy(name="blob", summary="b", load_template=lambda: template, population=lambda: list(axes),
                   load_subject=lambda sid: blob(axes[sid], sid), model_path=str(tmp_path / "blob.npz"))


def test_build_model_decides_its_modes_stores_the_figures_and_info_reads_them(tmp_path, monkeypatch):
    from clgs.cli.anatomy_group import make_group
    from clgs.shape.model import load_model, read_metadata
    from clgs.shape.modes import choose_modes

    axes = {"a": (14, 9, 8), "b": (16, 9, 7), "c": (15, 10, 8), "d": (13, 8.5, 7.5), "e": (16, 10, 8.5)}
    anatomy = _blob_anatomy(tmp_path, axes)
    group = make_group(anatomy)
    r = CliRunner().invoke(group, ["build-model", "--max-cells", "6"])
    assert r.exit_code == 0, r.output
    meta = read_metadata(tmp_path / "blob.npz")
    fig, choice = meta["statistics"], meta["mode_choice"]
    assert fig["modes"] == [1, 2, 3] and len(fig["compactness_all"]) == 4  # N - 2 figures, N - 1 modes
    assert all(np.isfinite(fig[k]).all() for k in ("compactness", "generalisation_mm", "specificity_mm"))
    assert fig["generalisation_mm"][0] >= fig["generalisation_mm"][-1] - 1e-9
    # the model keeps what the rule decides from the stored figures, and says why
    assert choice == choose_modes(fig, 4, 0.95, 0.05)
    model = load_model(tmp_path / "blob.npz")[0]
    assert model.n_modes == choice["n_modes"] == meta["n_modes"]
    # what lies beyond the kept modes for a left-out subject, kept for the surface's uncertainty
    assert model.beyond_cov.shape == (6,) + model.shape and model.beyond_cov[:3].max() > 0
    assert "compactness" in r.output and "generalisation" in r.output and "specificity" in r.output
    assert f"modes kept: {choice['n_modes']} (" in r.output
    # an override: exactly 4 modes, and the variance rule alone keeps what 95 % needs
    r = CliRunner().invoke(group, ["build-model", "--max-cells", "6", "--n-modes", "4"])
    assert r.exit_code == 0, r.output
    assert read_metadata(tmp_path / "blob.npz")["n_modes"] == 4 and "4 modes as asked" in r.output
    # written to the plugin's own file, which every command of the anatomy then uses: said so
    assert "plugin's model file now holds a model built with max_cells=6, n_modes=4" in r.output
    r = CliRunner().invoke(group, ["build-model", "--max-cells", "6", "--generalisation-tol", "0"])
    meta = read_metadata(tmp_path / "blob.npz")
    need = next(i + 1 for i, c in enumerate(meta["statistics"]["compactness_all"]) if c >= 0.95 - 1e-12)
    assert r.exit_code == 0 and meta["n_modes"] == need

    # a bad rule is refused before any registration
    calls = []
    anatomy.load_subject = calls.append
    r = CliRunner().invoke(make_group(anatomy), ["build-model", "--max-cells", "6", "--force",
                                                 "--generalisation-tol", "-1"])
    assert r.exit_code != 0 and "tolerance must be >= 0" in r.output and not calls

    # info reads the figures from the file: the surfaces are never asked for
    class NoSurfaces:
        def mesh(self, sid):
            raise AssertionError("info recomputed the figures")

    anatomy.population_model = NoSurfaces()
    r = CliRunner().invoke(make_group(anatomy), ["info"])
    assert r.exit_code == 0, r.output
    assert "velocity PCA at" in r.output and "specificity" in r.output and "modes kept" in r.output
