"""The import's calibration against known answers: simulated raw counts of an analytic phantom
(tests/raw_phantom.py) through the import path, the rotation axis anywhere within 15 pixels of the
middle, a uniform background, a 20 % beam drift, an object crossing the detector's edge, 180- and
360-degree arcs, a rolled detector, ring stripes and zingers; the axis within 0.5 px and the roll
within 0.2 degrees every time. Also the air normalisation, the estimators' disagreement warning
and NeXus NXtomo files."""
import re

import numpy as np
import pytest
from click.testing import CliRunner
from raw_phantom import line_integrals, raw_counts, rolled_geometry

from clgs.cli import main
from clgs.io.air import air_background, find_air, normalise_air
from clgs.io.artefacts import remove_stripes, remove_zingers
from clgs.io.raw import RawError, RawProjections, read_raw, scan_from_raw
from clgs.io.scan import Scan

COLS = 96


def _import(axis, *, n=90, rows=8, arc=180.0, endpoint=False, roll=0.0, beam=None, stripes=None, scale=1.0,
            seed=1, **kw):
    """(scan, report, true line integrals, angles in degrees) of a simulated scan imported."""
    geo, theta = rolled_geometry(n, rows, COLS, axis, roll, arc, endpoint)
    p = line_integrals(geo, scale=scale)
    counts, flats, darks = raw_counts(p, beam=beam, stripes=stripes, seed=seed)
    deg = np.rad2deg(theta)
    scan, report = scan_from_raw(RawProjections(counts, flats, darks), angles_deg=deg, **kw)
    return scan, report, p, deg


def _column(scan):
    g = scan.geometry
    return (g.nDetector[1] - 1) / 2 - g.offDetector[1] / g.dDetector[1]


@pytest.mark.parametrize("shift", [-15.0, -7.3, 0.0, 6.6, 15.0])
def test_the_axis_is_found_wherever_it_is(shift):
    axis = (COLS - 1) / 2 + shift
    scan, report, _, _ = _import(axis)
    c = report["centre"]
    assert abs(_column(scan) - axis) < 0.5, c
    for key in c["counted"]:  # every estimator, not only the chosen one
        assert abs(c["estimates"][key]["column"] - axis) < 0.5, (key, c["estimates"][key])
    assert c["agree"] and "warning" not in c and c["chosen"] == "pair"


def test_a_uniform_background_moves_nothing():
    axis = 40.3
    # the beam during the scan 24 % weaker than during the flats: 0.27 of background everywhere
    scan, report, p, _ = _import(axis, beam=np.full(90, np.exp(-0.27)))
    assert abs(report["air"]["background_mean"] - 0.27) < 0.01
    assert abs(_column(scan) - axis) < 0.5 and report["centre"]["agree"]
    assert abs(report["centre"]["estimates"]["com"]["column"] - axis) < 0.5
    assert np.abs(scan.projections - p).mean() < 0.01  # the background is gone
    # without the normalisation the centre of mass still removes the background it sees
    scan, report, _, _ = _import(axis, beam=np.full(90, np.exp(-0.27)), air=False)
    com = report["centre"]["estimates"]["com"]
    assert abs(com["column"] - axis) < 0.5 and com["background_removed_min"] > 0.25


def test_a_beam_drifting_by_20_percent_leaves_no_disk():
    from clgs.ct.fdk import fdk

    axis = 52.4
    beam = np.linspace(1.0, 0.8, 90)
    scan, report, p, _ = _import(axis, rows=4, beam=beam)
    air = report["air"]
    assert air["background_min"] < 0.01 and abs(air["background_max"] + np.log(0.8)) < 0.01
    assert len(air["background_per_view"]) == 90
    assert abs(_column(scan) - axis) < 0.5 and report["centre"]["agree"]
    raw, _, _, _ = _import(axis, rows=4, beam=beam, air=False, centre=axis)
    yy, xx = np.mgrid[:COLS, :COLS] - (COLS - 1) / 2
    ring = (np.hypot(yy, xx) > 33) & (np.hypot(yy, xx) < 40)  # air, inside the field of view
    good = fdk(scan.projections, scan.geometry)[1:3]
    bad = fdk(raw.projections, raw.geometry)[1:3]
    assert abs(good[:, ring].mean()) < 0.1 * bad[:, ring].mean()  # the disk: a raised field of view


def test_an_object_crossing_the_detector_edge():
    axis = 26.0
    scan, report, p, _ = _import(axis, scale=1.4)
    assert (p[:, :, 0] > 0.05).any()  # it does cross the edge
    c = report["centre"]
    assert abs(_column(scan) - axis) < 0.5
    assert not c["estimates"]["com"]["counted"] and "edge" in c["estimates"]["com"]["why_not_counted"]


@pytest.mark.parametrize("arc,n,endpoint", [(180.0, 90, False), (180.0, 91, True), (360.0, 120, False)])
def test_arcs_of_180_and_360_degrees(arc, n, endpoint):
    axis = 55.7
    scan, report, _, _ = _import(axis, n=n, arc=arc, endpoint=endpoint)
    c = report["centre"]
    assert abs(_column(scan) - axis) < 0.5 and c["agree"]
    pair = c["estimates"]["pair"]
    assert len(pair["pairs"]) == (8 if arc == 360 else 1)
    assert (abs(pair["gap_deg"]) > 1) == (not endpoint and arc == 180)


def test_a_rolled_detector_is_found_and_applied():
    axis, roll = 44.0, 1.0
    scan, report, _, _ = _import(axis, rows=24, roll=roll)
    assert abs(report["tilt"]["estimated_deg"] - roll) < 0.2 and report["tilt"]["applied_deg"] is None
    assert abs(_column(scan) - axis) < 0.5 and scan.geometry.is_circular
    scan, report, _, _ = _import(axis, rows=24, roll=roll, tilt="auto")
    assert abs(report["tilt"]["applied_deg"] - roll) < 0.2 and not scan.geometry.is_circular
    truth, _ = rolled_geometry(90, 24, COLS, axis, roll)
    got, want = scan.geometry.frame_vectors(), truth.frame_vectors()
    assert np.allclose(got[:, 0:3], want[:, 0:3])
    assert np.abs(got[:, 6:12] - want[:, 6:12]).max() < np.deg2rad(0.2)  # the pixel steps, turned alike
    # the axis (x = y = 0) lands on the same pixels: detector centres agree along u within 0.5 px
    assert np.abs(np.sum((got[:, 3:6] - want[:, 3:6]) * want[:, 6:9], 1)).max() < 0.5
    scan, report, _, _ = _import(axis, rows=24, roll=roll, tilt=0.7, centre=axis)
    assert report["tilt"]["applied_deg"] == 0.7


def test_ring_stripes_are_removed_and_move_nothing():
    from scipy import ndimage

    cols, axis = 128, 66.8
    geo, theta = rolled_geometry(90, 4, cols, axis)
    p = ndimage.gaussian_filter1d(line_integrals(geo, scale=1.4), 1.0, axis=2)  # a detector's blur
    where = [27, 50, 51, 82, 93]
    stripes = np.zeros(cols)
    stripes[where] = [0.04, -0.03, -0.03, 0.05, -0.04]
    raw = RawProjections(*raw_counts(p, stripes=stripes))
    deg = np.rad2deg(theta)
    scan, report = scan_from_raw(raw, angles_deg=deg, rings=5)
    plain, _ = scan_from_raw(raw, angles_deg=deg, centre=axis)
    assert abs(_column(scan) - axis) < 0.5 and report["rings"]["size"] == 5
    err, before = (np.abs((s.projections - p).mean(axis=0)) for s in (scan, plain))  # a stripe: in every view
    assert err[:, where].max() < 0.5 * before[:, where].max()
    assert np.percentile(np.delete(err, where, axis=1), 95) < 0.01  # and the rest left alone


def test_zingers_are_removed():
    rng = np.random.default_rng(3)
    geo, theta = rolled_geometry(30, 6, 64, 31.5)
    p = line_integrals(geo)
    counts, flats, darks = raw_counts(p, noise=False)
    where = (rng.integers(0, 30, 40), rng.integers(0, 6, 40), rng.integers(1, 63, 40))
    counts[where] *= 3.0  # a stray photon burst: far brighter than its neighbours
    raw = RawProjections(counts, flats, darks)
    scan, report = scan_from_raw(raw, angles_deg=np.rad2deg(theta), zingers="auto", centre=31.5)
    z = report["zingers"]
    assert 38 <= z["pixels"] <= 60  # the zingers, and few else
    err = np.abs(scan.projections - p)[where]  # log(3) = 1.1 before; the neighbourhood's median after
    assert err.mean() < 0.05 and err.max() < 0.35
    out, rep = remove_zingers(p.astype(np.float32), 0.5)
    assert rep["pixels"] == 0 and rep["threshold_from"] == "given"
    with pytest.raises(ValueError, match="positive number"):
        remove_zingers(p, -1.0)
    with pytest.raises(ValueError, match="odd"):
        remove_stripes(p, 4)


def test_air_normalisation_finds_the_air_of_each_view():
    geo, _ = rolled_geometry(12, 4, 80, 39.5)
    p = line_integrals(geo)
    offsets = np.linspace(-0.1, 0.3, 12)
    air = find_air(p + offsets[:, None, None])
    assert air[:, :5].all() and air[:, -5:].all() and not air[:, 39].any()
    out, report = normalise_air(p + offsets[:, None, None])
    assert np.allclose(report["background_per_view"], offsets, atol=1e-4)
    assert np.abs(out - p).max() < 1e-4
    bg, report = air_background(p + 0.2, air_columns=(0, 4))
    assert np.allclose(bg, 0.2) and report["air"] == "columns 0:4"
    with pytest.raises(ValueError, match="no view shows air"):
        air_background(np.ones((3, 2, 40)) + np.arange(40))
    with pytest.raises(ValueError, match="outside"):
        air_background(p, air_columns=(70, 90))


def test_disagreeing_estimators_warn_with_every_figure(tmp_path):
    geo, theta = rolled_geometry(90, 8, COLS, 47.0)
    p = line_integrals(geo)
    p[0] = np.roll(p[0], 6, axis=1)  # the first view moved: its pair with the last is wrong by 3 px
    counts, flats, darks = raw_counts(p)
    np.save(tmp_path / "counts.npy", counts)
    np.save(tmp_path / "flats.npy", flats)
    np.save(tmp_path / "darks.npy", darks)
    (tmp_path / "angles.txt").write_text("\n".join(f"{a:.6f}" for a in np.rad2deg(theta)))
    res = CliRunner().invoke(main, ["import", str(tmp_path / "counts.npy"), "--out", str(tmp_path / "scan"),
                                    "--flats", str(tmp_path / "flats.npy"), "--darks", str(tmp_path / "darks.npy"),
                                    "--angles", str(tmp_path / "angles.txt")])
    assert res.exit_code == 0, res.output
    assert "warning: the axis estimators disagree" in res.output and "--centre COLUMN" in res.output
    for name in ("180-degree pair", "FBP sharpness", "centre of mass"):
        assert re.search(name + r" +\d+\.\d\d", res.output), res.output
    assert "residual 0.0" not in res.output.split("rotation axis")[1].split("\n")[0]
    meta = Scan.load(tmp_path / "scan").meta["provenance"]["import"]["centre"]
    assert not meta["agree"] and meta["chosen"] == "sinogram" and abs(meta["column"] - 47.0) < 0.5
    assert set(meta["estimates"]) == {"pair", "sinogram", "com"}


def _write_nxtomo(path, counts, flats, darks, angles_deg, units="degree"):
    import h5py

    frames = np.concatenate([darks, flats[:2], counts, flats[2:]])
    keys = np.array([2] * len(darks) + [1] * 2 + [0] * len(counts) + [1] * (len(flats) - 2))
    angles = np.concatenate([np.zeros(len(darks) + 2), angles_deg, np.full(len(flats) - 2, angles_deg[-1])])
    if units.startswith("rad"):
        angles = np.deg2rad(angles)
    with h5py.File(path, "w") as f:
        entry = f.create_group("scan_1")
        entry.attrs["NX_class"] = "NXentry"
        entry["definition"] = "NXtomo"
        inst = entry.create_group("instrument")
        inst.attrs["NX_class"] = "NXinstrument"
        det = inst.create_group("pco")
        det.attrs["NX_class"] = "NXdetector"
        det["data"] = frames
        det["image_key"] = keys
        sample = entry.create_group("sample")
        sample.attrs["NX_class"] = "NXsample"
        sample["rotation_angle"] = angles
        sample["rotation_angle"].attrs["units"] = units


@pytest.mark.parametrize("units", ["degree", "rad"])
def test_nxtomo_files_import_like_data_exchange(tmp_path, units):
    geo, theta = rolled_geometry(90, 4, COLS, 41.2)
    p = line_integrals(geo)
    counts, flats, darks = raw_counts(p)
    deg = np.rad2deg(theta)
    _write_nxtomo(tmp_path / "scan.nxs", counts, flats, darks, deg, units)
    raw = read_raw(tmp_path / "scan.nxs")
    assert raw.data.shape == counts.shape and len(raw.flats) == 3 and len(raw.darks) == 2
    assert np.allclose(raw.angles_deg, deg) and np.array_equal(raw.data, counts)
    res = CliRunner().invoke(main, ["import", str(tmp_path / "scan.nxs"), "--out", str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    assert "NXtomo (/scan_1/instrument/pco/data)" in res.output
    assert abs(_column(Scan.load(tmp_path / "s")) - 41.2) < 0.5


def test_bad_nxtomo_files_are_named(tmp_path):
    import h5py

    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["x"] = np.zeros((2, 2, 2))
    with pytest.raises(RawError, match="neither the Data Exchange layout.*NXtomo"):
        read_raw(tmp_path / "plain.h5")
    geo, theta = rolled_geometry(8, 2, 32, 15.5)
    counts, flats, darks = raw_counts(line_integrals(geo))
    _write_nxtomo(tmp_path / "bad.nxs", counts, flats, darks, np.rad2deg(theta), units="furlong")
    with pytest.raises(RawError, match="unknown angle units 'furlong'"):
        read_raw(tmp_path / "bad.nxs")
    with h5py.File(tmp_path / "bad.nxs", "a") as f:
        del f["scan_1/instrument/pco/image_key"]
        f["scan_1/instrument/pco/image_key"] = np.full(len(counts) + 5, 7)
    with pytest.raises(RawError, match="image keys \\[7\\]"):
        read_raw(tmp_path / "bad.nxs")


def test_cli_options_are_checked(tmp_path):
    np.save(tmp_path / "c.npy", np.ones((4, 2, 8), np.float32))
    for args, msg in [(["--tilt", "sideways"], "'auto' or degrees"), (["--zingers", "-2"], "positive difference"),
                      (["--rings", "4"], "odd number"), (["--air-columns", "a:b"], "whole numbers")]:
        res = CliRunner().invoke(main, ["import", str(tmp_path / "c.npy"), "--out", str(tmp_path / "s"),
                                        "--arc", "180", *args])
        assert res.exit_code == 2 and msg in res.output, res.output
