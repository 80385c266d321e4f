"""``clgs.simulate``: the one simulation behind ``clgs simulate`` (the same bits from Python and
from the command line), checked against a known answer, HU in, and clear errors."""
import numpy as np
import pytest
from cli_helpers import run

import clgs
from clgs.errors import InputError
from clgs.io.scan import Scan


def _cube(n=24, mu=0.02):
    v = np.zeros((n, n, n), np.float32)
    v[n // 4:3 * n // 4, n // 4:3 * n // 4, n // 4:3 * n // 4] = mu
    return v


def test_python_and_command_line_give_the_same_scan(tmp_path):
    v = _cube()
    np.save(tmp_path / "v.npy", v)
    run("simulate", tmp_path / "v.npy", "--spacing", 2, "--views", 6, "--detector", 32, "--seed", 5,
        "--out", tmp_path / "cli")
    cli = Scan.load(tmp_path / "cli")
    py = clgs.simulate(v, spacing=2.0, views=6, detector=32, seed=5, progress=False)
    np.testing.assert_array_equal(py.projections, cli.projections)
    np.testing.assert_array_equal(py.truth, cli.truth)
    assert py.geometry.to_dict() == {k: v for k, v in cli.geometry.to_dict().items()}
    assert py.meta["acquisition"] == {k: cli.meta["acquisition"][k] for k in py.meta["acquisition"]}


def test_a_cube_seen_edge_on_has_its_known_line_integral():
    """Parallel beam, no noise: the central ray through a 12-voxel cube of 2 mm voxels at 0.02/mm
    crosses 24 mm of it: 0.48 (the fine protocol resamples, the centre stays exact)."""
    s = clgs.simulate(_cube(), spacing=2.0, views=4, mode="parallel", detector=33, pixel=2.0, noise=False,
                      progress=False)
    centre = s.projections[0, 16, 16]
    assert centre == pytest.approx(0.48, rel=2e-3)
    assert float(s.projections[0, 16, 0]) == pytest.approx(0.0, abs=1e-6)  # air beside it


def test_hounsfield_units_in():
    hu = np.full((16, 16, 16), -1000.0, np.float32)
    hu[4:12, 4:12, 4:12] = 0.0  # water in air
    s = clgs.simulate(hu, spacing=1.0, hu=True, kev=70, views=3, detector=24, noise=False, progress=False)
    np.testing.assert_allclose(s.truth, clgs.hu_to_mu(hu, 70), rtol=1e-6)
    assert s.meta["acquisition"]["kev"] == 70.0
    np.testing.assert_allclose(clgs.mu_to_hu(clgs.hu_to_mu(hu, 80), 80), hu, atol=1e-3)


@pytest.mark.parametrize("kwargs, message", [
    ({"spacing": None}, "without voxel size"),
    ({"spacing": -1.0}, "spacing must be positive"),
    ({"spacing": 1.0, "grid": 8, "grid_spacing": 2.0}, "not both"),
])
def test_clear_errors(kwargs, message):
    with pytest.raises(InputError, match=message):
        clgs.simulate(_cube(8), views=2, detector=8, progress=False, **kwargs)
    bad = _cube(8)
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        clgs.simulate(bad, spacing=1.0, views=2, detector=8, progress=False)
    with pytest.raises(InputError, match="negative values"):
        clgs.simulate(-_cube(8), spacing=1.0, views=2, detector=8, progress=False)
