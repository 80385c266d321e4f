"""Raw counts into line integrals (flat/dark, -log, floor, crop, bin), the rotation centre, the
formats (HDF5 Data Exchange, TIFF, .npy), clear errors, and the real tooth scan from the CLI."""
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from clgs.cli import main
from clgs.geometry import Geometry
from clgs.io.raw import RawError, RawProjections, crop_and_bin, find_centre, line_integrals, read_raw, scan_from_raw
from clgs.io.scan import Scan

TOOTH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "tooth" / "tooth.h5"
N, ROWS, COLS, AXIS = 36, 3, 48, 21.0  # the rotation axis projects to column 21 (middle: 23.5)


def _counts(seed=0):
    """Raw counts of a small off-centre object, with flats and darks, and the true line integrals."""
    from clgs.ops.ct_projector import CTProjector

    off_u = ((COLS - 1) / 2 - AXIS) * 1.0
    geo = Geometry(mode="parallel", DSD=1500.0, DSO=1000.0, nDetector=(ROWS, COLS), dDetector=(1.0, 1.0),
                   nVoxel=(ROWS, COLS, COLS), dVoxel=(1.0, 1.0, 1.0), offDetector=(0.0, off_u),
                   angles=np.deg2rad(np.arange(N) * 180.0 / N))
    zz, yy, xx = np.mgrid[:ROWS, :COLS, :COLS]
    vol = np.where(((yy - 27.0) ** 2 + (xx - 20.0) ** 2) < 36, 0.05, 0.0).astype(np.float32)
    vol += np.where(((yy - 18.0) ** 2 + (xx - 25.0) ** 2) < 9, 0.03, 0.0).astype(np.float32)
    p = CTProjector(geo).forward(vol)
    rng = np.random.default_rng(seed)
    gain = rng.uniform(0.8, 1.2, (ROWS, COLS))  # a flat field with structure, as a real detector has
    dark = rng.uniform(90.0, 110.0, (ROWS, COLS))
    flats = np.stack([dark + 3e4 * gain] * 4).astype(np.float32)
    darks = np.stack([dark] * 3).astype(np.float32)
    data = (dark + 3e4 * gain * np.exp(-p)).astype(np.float32)
    return data, flats, darks, p, geo


def test_flat_dark_log_gives_back_the_line_integrals():
    data, flats, darks, p, _ = _counts()
    proj, report = line_integrals(RawProjections(data, flats, darks))
    assert np.abs(proj - p).max() < 2e-4 and report["floored_pixels"] == 0
    assert report["flats"] == 4 and report["darks"] == 3 and report["I0"] == "flat fields"


def test_starved_pixels_are_floored_and_counted():
    data, flats, darks, _, _ = _counts()
    data[0, 0, :5] = darks[0, 0, :5]  # no photons at all
    data[1, 1, 2] = 0.0  # below the dark: a dead pixel
    proj, report = line_integrals(RawProjections(data, flats, darks), floor=1e-4)
    assert report["floored_pixels"] == 6
    assert np.allclose(proj[0, 0, :5], -np.log(1e-4)) and np.isfinite(proj).all()


def test_without_flats_i0_comes_from_air():
    _, _, darks, p, _ = _counts()
    uniform = (darks.mean(0) + 3e4 * np.exp(-p)).astype(np.float32)  # a uniform beam: air columns give I0
    proj, report = line_integrals(RawProjections(uniform, None, darks), air_columns=(0, 3))
    assert report["I0"] == "air columns 0-2" and np.abs(proj - p).max() < 1e-3
    proj, report = line_integrals(RawProjections(uniform, None, darks))
    assert report["I0"].startswith("brightest") and np.abs(proj - p).max() < 1e-3


def test_the_centre_is_found():
    data, flats, darks, p, geo = _counts()
    column, report = find_centre(p, geo.angles)
    assert abs(column - AXIS) < 0.25, column
    assert abs(report["estimates"]["com"]["column"] - AXIS) < 0.05 and report["agree"]
    assert not report["estimates"]["pair"]["available"]  # 5-degree steps: no view has an opposite
    with pytest.raises(RawError, match="cannot be found.*--centre"):
        find_centre(p[:4], geo.angles[:4])


def test_crop_and_bin():
    p = np.arange(2 * 4 * 6, dtype=np.float32).reshape(2, 4, 6)
    out = crop_and_bin(p, crop=(0, 4, 1, 5), binning=(2, 2))
    assert out.shape == (2, 2, 2) and out[0, 0, 0] == np.mean([1, 2, 7, 8])
    with pytest.raises(RawError, match="outside"):
        crop_and_bin(p, crop=(0, 5, 0, 6))
    with pytest.raises(RawError, match="larger"):
        crop_and_bin(p, binning=(8, 1))


def _write_h5(path, data, flats, darks, theta_deg):
    import h5py

    with h5py.File(path, "w") as f:
        f["exchange/data"] = data
        f["exchange/data_white"] = flats
        f["exchange/data_dark"] = darks
        f["exchange/theta"] = theta_deg


@pytest.mark.parametrize("kind", ["h5", "tiff-folder", "tiff-stack", "npy"])
def test_every_format_imports_to_the_same_scan(tmp_path, kind):
    import tifffile

    data, flats, darks, p, geo = _counts()
    theta = np.arange(N) * 180.0 / N
    args = []
    if kind == "h5":
        raw = tmp_path / "scan.h5"
        _write_h5(raw, data, flats, darks, theta)
    else:
        if kind == "tiff-folder":
            raw = tmp_path / "proj"
            raw.mkdir()
            for i, im in enumerate(data):
                tifffile.imwrite(raw / f"p{i:04d}.tif", im)
        elif kind == "tiff-stack":
            raw = tmp_path / "proj.tif"
            tifffile.imwrite(raw, data, photometric="minisblack")
        else:
            raw = tmp_path / "proj.npy"
            np.save(raw, data)
        tifffile.imwrite(tmp_path / "flats.tif", flats, photometric="minisblack")
        np.save(tmp_path / "darks.npy", darks)
        args = ["--flats", tmp_path / "flats.tif", "--darks", tmp_path / "darks.npy", "--arc", 180]
    res = CliRunner().invoke(main, ["import", str(raw), "--out", str(tmp_path / "scan"), *map(str, args)])
    assert res.exit_code == 0, res.output
    assert re.search(r"rotation axis at column (20\.9|21\.0|21\.1)", res.output), res.output
    scan = Scan.load(tmp_path / "scan")
    assert np.abs(scan.projections - p).max() < 2e-4
    assert np.allclose(scan.geometry.angles, geo.angles)
    assert abs(scan.geometry.offDetector[1] - geo.offDetector[1]) < 0.05


def test_bad_raw_input_is_named(tmp_path):
    import tifffile

    data, flats, darks, _, _ = _counts()
    folder = tmp_path / "mixed"
    folder.mkdir()
    tifffile.imwrite(folder / "a.tif", data[0])
    tifffile.imwrite(folder / "b.tif", data[0][:, :10])
    with pytest.raises(RawError, match="different sizes.*b.tif"):
        read_raw(folder)
    with pytest.raises(RawError, match="darker than"):
        line_integrals(RawProjections(data, darks[:1] * 0 + 1.0, darks))
    raw = RawProjections(data, flats, darks)
    with pytest.raises(RawError, match="5 angles for 36 projections"):
        scan_from_raw(raw, angles_deg=np.arange(5.0))
    with pytest.raises(RawError, match="no angles"):
        scan_from_raw(raw)
    with pytest.raises(RawError, match="centre column"):
        scan_from_raw(raw, arc_deg=180, centre=500.0)
    np.save(tmp_path / "x.npy", data)
    with pytest.raises(RawError, match="must match"):
        read_raw(tmp_path / "x.npy", flats=folder / "b.tif")
    res = CliRunner().invoke(main, ["import", str(tmp_path / "nothing.h5"), "--out", str(tmp_path / "s")])
    assert res.exit_code == 1 and "no such file" in res.output


@pytest.mark.skipif(not TOOTH.is_file(), reason="the tooth data set sits in shared/data")
def test_the_real_tooth_imports_and_reconstructs(tmp_path):
    res = CliRunner().invoke(main, ["import", str(TOOTH), "--out", str(tmp_path / "tooth")])
    assert res.exit_code == 0, res.output
    scan = Scan.load(tmp_path / "tooth")
    column = (scan.geometry.nDetector[1] - 1) / 2 - scan.geometry.offDetector[1] / scan.geometry.dDetector[1]
    assert 290 <= column <= 300  # the README of the data: about column 290-300
    c = scan.meta["provenance"]["import"]["centre"]
    # views 0 and 180 (179 degrees apart) are the pair; every estimator within 0.5 px of it
    assert c["chosen"] == "pair" and c["estimates"]["pair"]["pairs"] == [[0, 180]] and c["agree"]
    assert all(abs(c["estimates"][k]["column"] - c["column"]) < 0.5 for k in ("sinogram", "com"))
    res = CliRunner().invoke(main, ["reconstruct", str(tmp_path / "tooth"), "--method", "fdk",
                                    "--out", str(tmp_path / "fdk.nii.gz")])
    assert res.exit_code == 0, res.output
