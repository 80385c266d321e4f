"""Acquisition noise model: count statistics, scatter ratio, seeds, bad input."""
import numpy as np
import pytest

from clgs.ct.noise import add_noise, expected_counts, simulate_counts


def test_flat_field_counts_match_the_model():
    """200k pixels of one flat field: sample mean and variance of the counts agree with
    mean = I0 exp(-p / max_p), variance = mean + sigma^2, within 5 standard errors."""
    I0, sigma, p, max_p = 2000.0, 15.0, 1.3, 4.0
    flat = np.full((2, 250, 400), p)
    counts, used = simulate_counts(flat, I0=I0, sigma=sigma, seed=1, max_p=max_p)
    assert used == max_p
    n = counts.size
    mean = I0 * np.exp(-p / max_p)
    var = mean + sigma**2
    assert abs(counts.mean() - mean) < 5 * np.sqrt(var / n)
    assert abs(counts.var() - var) < 5 * var * np.sqrt(2.0 / n)
    # the Poisson part alone (sigma = 0) has variance equal to its mean
    c0, _ = simulate_counts(flat, I0=I0, sigma=0.0, seed=2, max_p=max_p)
    assert abs(c0.var() / c0.mean() - 1) < 5 * np.sqrt(2.0 / n)


def test_line_integrals_round_trip():
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 3, (3, 20, 30))
    noisy = add_noise(p, I0=1e5, sigma=5.0, seed=7)
    counts, max_p = simulate_counts(p, I0=1e5, sigma=5.0, seed=7)
    assert max_p == pytest.approx(p.max())
    np.testing.assert_array_equal(noisy, (-np.log(counts / 1e5) * max_p).astype(np.float32))
    # relative noise of the intensity ~ 1/sqrt(counts): line integral error ~ max_p / sqrt(I)
    err = (noisy - p) / (max_p / np.sqrt(1e5 * np.exp(-p / max_p)))
    assert 0.8 < err.std() < 1.2 and abs(err.mean()) < 0.1
    # no noise at all: a huge I0 and no electronics give back the input
    clean = add_noise(p, I0=1e12, sigma=0.0, seed=0)
    np.testing.assert_allclose(clean, p, atol=1e-4)


def test_seeds():
    p = np.random.default_rng(0).uniform(0, 2, (2, 16, 16))
    assert add_noise(p, seed=3).tobytes() == add_noise(p, seed=3).tobytes()
    assert add_noise(p, seed=3).tobytes() != add_noise(p, seed=4).tobytes()


def test_scatter_ratio_and_smoothness():
    yy, xx = np.mgrid[-1:1:64j, -1:1:80j]
    p = np.stack([3.0 * (xx**2 + yy**2 < 0.4), 2.0 * (np.abs(xx) < 0.3)])
    primary = expected_counts(p, I0=1e4)
    total = expected_counts(p, I0=1e4, scatter=0.25)
    scatter = total - primary
    for v in range(2):
        assert scatter[v].mean() / primary[v].mean() == pytest.approx(0.25, rel=1e-9)
        assert scatter[v].min() > 0
        # low frequency: far smoother than the primary image
        rough = lambda a: np.abs(np.diff(a, axis=1)).max() / a.mean()  # noqa: E731
        assert rough(scatter[v]) < 0.1 * rough(primary[v])
    # the Poisson counts follow the scatter-inclusive mean
    counts, _ = simulate_counts(np.repeat(p, 50, 0), I0=1e4, sigma=0.0, scatter=0.25, seed=5)
    assert counts.mean() == pytest.approx(np.repeat(total, 50, 0).mean(), rel=2e-3)
    # uncorrected scatter lowers the line integrals
    assert add_noise(p, I0=1e4, sigma=0, scatter=0.25).mean() < add_noise(p, I0=1e4, sigma=0).mean()


def test_counts_are_clipped_and_output_finite():
    p = np.full((1, 8, 8), 50.0)
    noisy = add_noise(p, I0=10.0, sigma=20.0, seed=0, max_p=1.0)  # almost no photons left
    assert np.isfinite(noisy).all()
    assert noisy.max() <= np.log(10.0) * 1.0 + 1e-6  # counts >= 1


def test_bad_input_is_a_clear_error():
    p = np.zeros((1, 4, 4))
    with pytest.raises(ValueError, match="NaN"):
        add_noise(np.full((1, 4, 4), np.nan))
    with pytest.raises(ValueError, match="at least one view"):
        add_noise(np.zeros((0, 4, 4)))
    with pytest.raises(ValueError, match="I0"):
        add_noise(p, I0=0)
    with pytest.raises(ValueError, match="sigma"):
        add_noise(p, sigma=-1)
    with pytest.raises(ValueError, match="scatter"):
        add_noise(p, scatter=-0.1)
    # an all-zero projection (nothing attenuates) is fine
    assert np.isfinite(add_noise(p)).all()
