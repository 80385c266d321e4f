"""DICOM CT series out (Hounsfield units, position kept) and the round trips a scanner's data
takes through clgs: DICOM -> simulate -> reconstruct -> DICOM, each at the same world points."""
import numpy as np
import pytest
from cli_helpers import run

from clgs.io.units import hu_to_mu, mu_to_hu
from clgs.io.volume import load_volume, save_volume

pytest.importorskip("SimpleITK")

ORIGIN = (-120.0, 40.0, 300.0)
SPACING = (3.0, 2.0, 1.5)  # (Z, Y, X)




@pytest.fixture(scope="module")
def ct(tmp_path_factory):
    """A small CT in attenuation: soft tissue with a dense off-centre block, placed off the origin."""
    d = tmp_path_factory.mktemp("dicom")
    mu = np.full((10, 12, 14), 0.019, np.float32)
    mu[3:7, 4:9, 2:6] = 0.045
    mu[0] = 0.0  # air: -1000 HU
    save_volume(d / "ct.nii.gz", mu, spacing=SPACING, origin=ORIGIN)
    return d, mu


def test_dicom_series_round_trip_keeps_position_and_hu(ct):
    d, mu = ct
    res = run("convert", d / "ct.nii.gz", d / "series", "--dicom", "--kev", 70)
    assert "10 DICOM slices" in res.output and "-1000 to" in res.output
    assert len(list((d / "series").glob("*.dcm"))) == 10
    hu, sp, org = load_volume(d / "series", dtype=None)
    assert hu.dtype == np.int16
    assert sp == pytest.approx(SPACING) and org == pytest.approx(ORIGIN, abs=1e-5)
    assert np.abs(hu - mu_to_hu(mu, 70.0)).max() <= 0.5 + 1e-6  # rounded to the nearest HU
    back = hu_to_mu(hu, 70.0)
    assert np.abs(mu_to_hu(back, 70.0) - mu_to_hu(mu, 70.0)).max() <= 0.5 + 1e-6
    # the same volume gives the same files (UIDs from the data), and an existing folder is kept
    res = run("convert", d / "ct.nii.gz", d / "series", "--dicom", ok=False)
    assert res.exit_code != 0 and "--force" in res.output


def test_hu_to_attenuation_and_back_within_half_a_hu(ct, tmp_path):
    d, mu = ct
    run("convert", d / "ct.nii.gz", tmp_path / "hu.nrrd", "--to-hu", "--kev", 90)
    run("convert", tmp_path / "hu.nrrd", tmp_path / "mu.mha", "--hu", "--kev", 90)
    run("convert", tmp_path / "mu.mha", tmp_path / "hu2.nii.gz", "--to-hu", "--kev", 90)
    a, _, org = load_volume(tmp_path / "hu.nrrd")
    b, _, org2 = load_volume(tmp_path / "hu2.nii.gz")
    assert org == pytest.approx(ORIGIN) and org2 == pytest.approx(ORIGIN)
    assert np.abs(a - b).max() < 0.5
    m, _, _ = load_volume(tmp_path / "mu.mha")
    np.testing.assert_allclose(m, mu, rtol=1e-5, atol=1e-7)


def test_a_scanners_dicom_series_through_clgs_stays_in_place(ct, tmp_path):
    """DICOM (HU) -> simulate --hu -> reconstruct -> DICOM: every volume on the input's grid."""
    d, mu = ct
    series = d / "series"
    if not series.exists():
        run("convert", d / "ct.nii.gz", series, "--dicom")
    run("simulate", series, "--hu", "--views", 12, "--detector", 32, "--no-noise", "--out", tmp_path / "scan")
    run("reconstruct", tmp_path / "scan", "--method", "fdk", "--out", tmp_path / "fdk.nii.gz")
    run("convert", tmp_path / "fdk.nii.gz", tmp_path / "fdk_series", "--dicom")
    for path in (tmp_path / "scan" / "truth.nii.gz", tmp_path / "fdk.nii.gz", tmp_path / "fdk_series"):
        _, sp, org = load_volume(path, dtype=None)
        assert sp == pytest.approx(SPACING) and org == pytest.approx(ORIGIN, abs=1e-5), path
    truth, _, _ = load_volume(tmp_path / "scan" / "truth.nii.gz")
    assert np.abs(mu_to_hu(truth, 70.0) - mu_to_hu(mu, 70.0)).max() <= 0.5 + 1e-3  # HU -> mu at 70 keV


def test_convert_refuses_what_it_cannot_write(ct, tmp_path):
    d, _ = ct
    res = run("convert", d / "ct.nii.gz", tmp_path / "noformat", ok=False)
    assert res.exit_code == 2 and "--dicom" in res.output
    bad = np.zeros((3, 3, 3), np.float32)
    bad[1, 1, 1] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    res = run("convert", tmp_path / "nan.npy", tmp_path / "o.nii.gz", "--spacing", 1, ok=False)
    assert res.exit_code != 0 and "NaN" in res.output
    res = run("convert", d / "ct.nii.gz", d / "ct.nii.gz", "--force", ok=False)
    assert res.exit_code != 0 and "ct.nii.gz" in res.output
