"""Compactness, generalisation and specificity of a surface PCA (clgs.shape.statistics), on
synthetic surfaces of known structure, against numpy's SVD."""
import numpy as np
import pytest


def _population(n=12, v=40, noise=0.01, seed=0):
    """Surfaces (n, v, 3) = a mean + two modes of known spread (10 and 4 mm) + small noise."""
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=(v, 3)) * 20
    modes = np.linalg.qr(rng.normal(size=(v * 3, 2)))[0].T
    coef = rng.normal(size=(n, 2)) * [10.0, 4.0]
    x = mean.reshape(-1) + coef @ modes + rng.normal(size=(n, v * 3)) * noise
    return x.reshape(n, v, 3)


def test_compactness_matches_numpys_svd_and_two_modes_hold_two_mode_surfaces():
    from clgs.shape.statistics import shape_space_figures

    x = _population()
    f = shape_space_figures(x, max_modes=4, n_samples=50)
    flat = x.reshape(len(x), -1)
    s = np.linalg.svd(flat - flat.mean(0), compute_uv=False)
    np.testing.assert_allclose(f["compactness"], np.cumsum(s ** 2)[:4] / np.sum(s ** 2), rtol=1e-10)
    assert f["compactness"][1] > 0.999 and f["modes"] == [1, 2, 3, 4]
    # the left-out surface is reached by two modes (down to the noise), not by one
    g = f["generalisation_mm"]
    assert g[0] > 10 * g[1] and g[1] < 0.05 and g[3] <= g[1] + 1e-9
    # specificity: random shapes of the two-mode model lie near real ones; it does not grow from 1 to 2
    # modes by more than the second mode's spread
    assert all(np.isfinite(f["specificity_mm"])) and f["specificity_mm"][1] < f["specificity_mm"][0] + 4.0


def test_bad_surfaces_are_refused():
    from clgs.errors import InputError
    from clgs.shape.statistics import shape_space_figures

    with pytest.raises(InputError, match="vertex correspondence"):
        shape_space_figures(np.zeros((4, 10)))
    with pytest.raises(InputError, match="at least 3"):
        shape_space_figures(np.zeros((2, 10, 3)))
    x = _population()
    x[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        shape_space_figures(x)


def test_info_prints_the_figures_for_an_anatomy_with_surfaces_in_correspondence():
    import click
    from click.testing import CliRunner

    from clgs.anatomy.record import Anatomy
    from clgs.cli.anatomy_group import _echo_shape_space

    x = _population(n=8)

    class Population:
        def mesh(self, sid):
            return x[int(sid)], np.zeros((1, 3), int)

    anatomy = Anatomy(name="twomodes", summary="x", population=lambda: [str(i) for i in range(8)])
    anatomy.population_model = Population()
    out = CliRunner().invoke(click.command()(lambda: _echo_shape_space(anatomy, max_modes=3)), [])
    assert out.exit_code == 0, out.output
    assert "PCA of the 8 population surfaces' vertices, modes 1 / 2 / 3" in out.output
    assert "compactness" in out.output and "generalisation" in out.output and "specificity" in out.output
