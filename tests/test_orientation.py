"""Outputs keep the input's array order and affine (LAS, LPS, permuted NIfTI files, a DICOM
series), and every volume says its units: checked with nibabel and SimpleITK, not with clgs's
own reader."""
import json

import numpy as np
import pytest
from cli_helpers import run

from clgs.io.orientation import file_affine, to_file, to_working
from clgs.io.volume import load_volume, save_volume

pytest.importorskip("clgs.ops.ct_projector")
nib = pytest.importorskip("nibabel")

# file affines (voxel i, j, k -> world x, y, z mm): dcm2niix's LAS, an axial DICOM's LPS, a permuted file
AFFINES = {
    "LAS": [[-2.5, 0, 0, 161.25], [0, 2.5, 0, -20.0], [0, 0, 2.5, 35.0]],
    "LPS": [[-2.0, 0, 0, 30.0], [0, -2.5, 0, 40.0], [0, 0, 3.0, -10.0]],
    "PSR": [[0, 0, 2.0, -15.0], [-2.5, 0, 0, 25.0], [0, 3.0, 0, 5.0]],
}


def asymmetric_object(shape):
    """Attenuation (1/mm) with no mirror symmetry: an off-centre ball and a bar along the first axis."""
    idx = np.indices(shape).astype(float)
    n = np.asarray(shape, float)[:, None, None, None]
    rel = (idx - 0.3 * n) / n
    vol = np.where((rel ** 2).sum(0) < 0.04, 0.02, 0.0)
    vol[1:-4, int(0.7 * shape[1]), int(0.6 * shape[2])] = 0.05
    return vol.astype(np.float32)


def _corr(a, b):
    return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def _centroid_world(data, affine):
    """The world position (mm) of an array's mass centre, through its own affine."""
    w = np.clip(np.asarray(data, float), 0, None)
    c = np.array([(np.indices(w.shape)[a] * w).sum() / w.sum() for a in range(3)])
    return (np.asarray(affine) @ np.append(c, 1.0))[:3]


@pytest.mark.parametrize("codes", sorted(AFFINES))
def test_save_volume_writes_the_file_order_back(tmp_path, codes):
    """Any orientation: read, then written with the file's codes, gives the file's affine and array."""
    aff = np.vstack([AFFINES[codes], [0, 0, 0, 1.0]])
    data = np.random.default_rng(1).random((5, 6, 7)).astype(np.float32)
    nib.save(nib.Nifti1Image(data, aff), str(tmp_path / "in.nii.gz"))
    got = load_volume(tmp_path / "in.nii.gz")
    assert got.orientation == "".join(nib.aff2axcodes(aff)) == codes
    assert np.array_equal(to_file(got.volume, codes), data.T) and np.array_equal(to_working(data.T, codes), got.volume)
    assert np.allclose(file_affine(got.spacing, got.origin, got.volume.shape, codes), aff)
    for suffix in (".nii.gz", ".npy", ".mha", ".nrrd"):
        save_volume(tmp_path / f"out{suffix}", got.volume, spacing=got.spacing, origin=got.origin,
                    orientation=got.orientation, units="1/mm")
    out = nib.load(str(tmp_path / "out.nii.gz"))
    assert np.allclose(out.affine, aff, atol=1e-9) and np.array_equal(out.get_fdata(), data)
    assert np.array_equal(np.load(tmp_path / "out.npy"), data.T)  # the NIfTI's array, axes reversed
    sitk = pytest.importorskip("SimpleITK")
    ref = sitk.ReadImage(str(tmp_path / "in.nii.gz"))
    for suffix in (".mha", ".nrrd"):
        img = sitk.ReadImage(str(tmp_path / f"out{suffix}"))
        assert np.allclose(img.GetDirection(), ref.GetDirection()) and np.allclose(img.GetOrigin(), ref.GetOrigin())
        assert np.allclose(img.GetSpacing(), ref.GetSpacing())
        assert np.array_equal(sitk.GetArrayFromImage(img), sitk.GetArrayFromImage(ref))
        assert img.GetMetaData("clgs_units") == "1/mm"


@pytest.mark.parametrize("codes", sorted(AFFINES))
def test_simulate_and_fdk_keep_the_input_order(tmp_path, codes):
    """simulate -> FDK: truth and reconstruction have the input's affine and array order."""
    aff = np.vstack([AFFINES[codes], [0, 0, 0, 1.0]])
    data = asymmetric_object((18, 20, 22))
    nib.save(nib.Nifti1Image(data, aff), str(tmp_path / "in.nii.gz"))
    run("simulate", tmp_path / "in.nii.gz", "--views", 40, "--detector", 48, "--no-noise", "--out", tmp_path / "scan")
    truth = nib.load(str(tmp_path / "scan" / "truth.nii.gz"))
    assert np.allclose(truth.affine, aff, atol=1e-6)
    assert np.array_equal(truth.get_fdata(dtype=np.float32), data)  # index by index, exactly
    assert np.array_equal(np.load(tmp_path / "scan" / "truth.npy"), data.T)
    assert truth.header["intent_name"].item() == b"mu 1/mm"
    doc = json.loads((tmp_path / "scan" / "scan.json").read_text())
    assert doc["geometry"]["orientation"] == codes and doc["version"] == 2 and doc["truth_units"] == "1/mm"
    prov = doc["meta"]["provenance"]
    assert prov["volume_orientation"] == codes and np.allclose(prov["volume_affine"], aff)
    assert prov["volume_shape"] == list(data.shape) and prov["volume_units"] == "1/mm"

    run("reconstruct", tmp_path / "scan", "--method", "fdk", "--out", tmp_path / "rec")
    rec = nib.load(str(tmp_path / "rec" / "volume.nii.gz"))
    assert np.allclose(rec.affine, aff, atol=1e-6) and rec.shape == data.shape
    arr = rec.get_fdata()
    assert _corr(arr, data) > 0.85  # by index
    assert np.array_equal(np.load(tmp_path / "rec" / "volume.npy"), arr.astype(np.float32).T)
    # by world position, each array through its own affine (nibabel's)
    assert np.linalg.norm(_centroid_world(arr, rec.affine) - _centroid_world(data, aff)) < 2.0
    report = json.loads((tmp_path / "rec" / "report.json").read_text())
    assert report["volume_units"] == {"units": "1/mm"} and report["volume_orientation"] == codes
    assert rec.header["descrip"].item().startswith(b"clgs: linear attenuation")
    # evaluate compares the .npy (file order) with the scan's truth in the right order
    res = run("evaluate", tmp_path / "rec" / "volume.npy", "--truth", tmp_path / "scan")
    res_nii = run("evaluate", tmp_path / "rec", "--truth", tmp_path / "scan")
    assert res.output.splitlines()[0] == res_nii.output.splitlines()[0]


def _write_dicom_series(folder, hu, spacing_xyz, origin_lps):
    """An axial CT series (int16 HU), one file per slice, with SimpleITK."""
    sitk = pytest.importorskip("SimpleITK")
    folder.mkdir()
    img = sitk.GetImageFromArray(hu.astype(np.int16))  # (z, y, x)
    img.SetSpacing(spacing_xyz)
    img.SetOrigin(origin_lps)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    series = "1.2.826.0.1.3680043.2.1125.1.42"
    for k in range(img.GetDepth()):
        sl = img[:, :, k]
        pos = img.TransformIndexToPhysicalPoint((0, 0, k))
        for tag, value in (("0008|0060", "CT"), ("0020|000e", series), ("0020|000d", series + ".1"),
                           ("0020|0037", "1\\0\\0\\0\\1\\0"), ("0020|0032", "\\".join(f"{p:g}" for p in pos)),
                           ("0020|0013", str(k + 1)), ("0018|0050", f"{spacing_xyz[2]:g}"),
                           ("0028|1052", "0"), ("0028|1053", "1")):
            sl.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"slice{k:03d}.dcm"))
        writer.Execute(sl)


def test_dicom_series_simulate_and_fdk_in_hu_keep_the_series_frame(tmp_path):
    """A DICOM series (LPS) in HU: truth and FDK (--to-hu) come back with the series' frame, index by
    index, as SimpleITK reads both."""
    sitk = pytest.importorskip("SimpleITK")
    from clgs.io.units import hu_to_mu

    mu = asymmetric_object((16, 20, 18))  # (z, y, x) as SimpleITK arrays are
    hu = np.round(1000.0 * (mu / 0.0193 - 1.0))
    _write_dicom_series(tmp_path / "series", hu, (2.0, 2.5, 3.0), (-20.0, 30.0, 100.0))
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(tmp_path / "series")))
    ref = reader.Execute()
    ref_hu = sitk.GetArrayFromImage(ref).astype(np.float32)
    assert np.array_equal(ref_hu, hu)
    run("simulate", tmp_path / "series", "--hu", "--kev", 80, "--views", 40, "--detector", 48, "--no-noise",
        "--out", tmp_path / "scan")
    truth = sitk.ReadImage(str(tmp_path / "scan" / "truth.nii.gz"))
    for got, want in ((truth.GetOrigin(), ref.GetOrigin()), (truth.GetDirection(), ref.GetDirection()),
                      (truth.GetSpacing(), ref.GetSpacing())):
        assert np.allclose(got, want, atol=1e-5)
    assert np.array_equal(sitk.GetArrayFromImage(truth), hu_to_mu(ref_hu, 80))
    doc = json.loads((tmp_path / "scan" / "scan.json").read_text())
    assert doc["geometry"]["orientation"] == "LPS" and doc["meta"]["acquisition"]["kev"] == 80
    # reconstruct in HU at the energy the scan records
    run("reconstruct", tmp_path / "scan", "--method", "fdk", "--to-hu", "--out", tmp_path / "rec.nii.gz",
        "--json", tmp_path / "rec.json")
    rec = sitk.ReadImage(str(tmp_path / "rec.nii.gz"))
    assert np.allclose(rec.GetDirection(), ref.GetDirection()) and np.allclose(rec.GetOrigin(), ref.GetOrigin())
    rec_hu = sitk.GetArrayFromImage(rec)
    assert _corr(rec_hu, ref_hu) > 0.85
    air = ref_hu < -900
    assert abs(float(np.median(rec_hu[air])) + 1000) < 100  # air reads about -1000 HU
    assert rec.GetMetaData("intent_name") == "HU 80 keV" and "Hounsfield" in rec.GetMetaData("descrip")
    report = json.loads((tmp_path / "rec.json").read_text())
    assert report["volume_units"]["units"] == "HU" and report["volume_units"]["kev"] == 80


def test_oblique_input_keeps_its_resampled_grid(tmp_path):
    """An oblique file is resampled onto an axis-aligned RAS grid: that grid is the input the
    outputs keep."""
    c, s = np.cos(0.3), np.sin(0.3)
    aff = np.array([[2 * c, -2 * s, 0, 0], [2 * s, 2 * c, 0, 0], [0, 0, 2.0, 0], [0, 0, 0, 1]])
    nib.save(nib.Nifti1Image(asymmetric_object((12, 12, 10)), aff), str(tmp_path / "obl.nii.gz"))
    with pytest.warns(UserWarning, match="oblique"):
        got = load_volume(tmp_path / "obl.nii.gz")
    assert got.orientation == "RAS"
    with pytest.warns(UserWarning, match="oblique"):
        run("simulate", tmp_path / "obl.nii.gz", "--views", 8, "--detector", 32, "--no-noise",
            "--out", tmp_path / "scan")
    truth = nib.load(str(tmp_path / "scan" / "truth.nii.gz"))
    assert np.allclose(truth.affine, file_affine(got.spacing, got.origin, got.volume.shape, "RAS"), atol=1e-6)
    assert np.array_equal(truth.get_fdata(dtype=np.float32), got.volume.T)


def test_older_scans_and_geometry_files_stay_ras(tmp_path):
    """A scan without the record (version 1, no orientation) reads and writes as before."""
    from clgs.geometry import Geometry, GeometryError
    from clgs.io.scan import Scan

    g = Geometry.default(n_views=3, n_voxel=8, n_detector=16, volume_mm=16.0)
    assert g.orientation == "RAS" and "orientation" not in g.to_dict()
    truth = asymmetric_object((8, 8, 8))
    Scan(g, np.zeros((3, 16, 16), np.float32), truth).save(tmp_path / "s")
    doc = json.loads((tmp_path / "s" / "scan.json").read_text())
    assert doc["version"] == 1 and np.array_equal(np.load(tmp_path / "s" / "truth.npy"), truth)
    lps = Geometry.from_dict({**g.to_dict(), "orientation": "lps"})
    assert lps.orientation == "LPS" and lps != g and lps.select([0, 1]).orientation == "LPS"
    assert lps.as_vectors().orientation == "LPS"
    Scan(lps, np.zeros((3, 16, 16), np.float32), truth).save(tmp_path / "l")
    assert np.array_equal(Scan.load(tmp_path / "l").truth, truth)
    assert np.array_equal(np.load(tmp_path / "l" / "truth.npy"), to_file(truth, "LPS"))
    for bad in ("RAX", "RRS", "RA", 5):
        with pytest.raises(GeometryError, match="orientation"):
            Geometry.from_dict({**g.to_dict(), "orientation": bad})


# ------------------------------------------------------------------------------ units
@pytest.fixture(scope="module")
def mu_scan(tmp_path_factory):
    """A scan simulated from a volume in 1/mm (so it records no X-ray energy)."""
    d = tmp_path_factory.mktemp("units")
    save_volume(d / "obj.nii.gz", asymmetric_object((16, 16, 16)), spacing=2.0)
    run("simulate", d / "obj.nii.gz", "--views", 24, "--detector", 32, "--no-noise", "--out", d / "scan")
    return d


def test_reconstruct_hu_needs_a_known_energy(mu_scan, tmp_path):
    from clgs.io.units import water_mu

    res = run("reconstruct", mu_scan / "scan", "--method", "fdk", "--to-hu", "--out", tmp_path / "hu", ok=False)
    assert res.exit_code == 2 and "records none" in res.output and "--kev" in res.output
    assert not (tmp_path / "hu").exists()
    res = run("reconstruct", mu_scan / "scan", "--method", "fdk", "--kev", 70, "--out", tmp_path / "x", ok=False)
    assert res.exit_code == 2 and "add --to-hu" in res.output
    run("reconstruct", mu_scan / "scan", "--method", "fdk", "--out", tmp_path / "mu")
    run("reconstruct", mu_scan / "scan", "--method", "fdk", "--to-hu", "--kev", 60, "--out", tmp_path / "hu")
    mu = nib.load(str(tmp_path / "mu" / "volume.nii.gz")).get_fdata()
    hu = nib.load(str(tmp_path / "hu" / "volume.nii.gz"))
    w = water_mu(60)
    assert np.allclose(hu.get_fdata(), 1000.0 * (mu - w) / w, atol=1e-2)  # HU = 1000 (mu - mu_water) / mu_water
    assert np.allclose(np.load(tmp_path / "hu" / "volume.npy"), hu.get_fdata().T)
    assert hu.header["intent_name"].item() == b"HU 60 keV"
    report = json.loads((tmp_path / "hu" / "report.json").read_text())
    assert report["volume_units"] == {"units": "HU", "kev": 60.0, "water_mu_per_mm": round(w, 6)}
    # the figures stay in 1/mm, against the truth
    mu_report = json.loads((tmp_path / "mu" / "report.json").read_text())
    assert report["metrics"]["psnr3d"] == pytest.approx(mu_report["metrics"]["psnr3d"])
    assert mu_report["volume_units"] == {"units": "1/mm"}


def test_save_reconstruction_from_python(mu_scan, tmp_path):
    from clgs.io.reconstruction import save_reconstruction
    from clgs.io.scan import Scan
    from clgs.io.units import UnitsError

    sc = Scan.load(mu_scan / "scan")
    with pytest.raises(UnitsError, match="records none"):
        save_reconstruction(tmp_path / "a.nii.gz", sc.truth, sc.geometry, hu=True, meta=sc.meta)
    rec = save_reconstruction(tmp_path / "a.nii.gz", sc.truth, sc.geometry, hu=True, kev=70)
    assert rec["units"] == "HU" and rec["kev"] == 70.0
    img = nib.load(str(tmp_path / "a.nii.gz"))
    assert img.get_fdata().min() == pytest.approx(-1000.0)  # air


def test_implausible_attenuation_is_named(tmp_path):
    """A volume normalised to [0, 1] taken as 1/mm: a warning says what was seen and what to pass."""
    vol = asymmetric_object((16, 16, 16)) / 0.05  # 0 .. 1
    save_volume(tmp_path / "norm.nii.gz", vol, spacing=2.0)
    res = run("simulate", tmp_path / "norm.nii.gz", "--views", 4, "--detector", 24, "--no-noise",
              "--out", tmp_path / "s")
    assert "99.9th percentile is 1/mm" in res.output and "--hu" in res.output
    save_volume(tmp_path / "ok.nii.gz", vol * 0.02, spacing=2.0)
    res = run("simulate", tmp_path / "ok.nii.gz", "--views", 4, "--detector", 24, "--no-noise",
              "--out", tmp_path / "t")
    assert "percentile" not in res.output
    from clgs.io.units import attenuation_doubt

    assert "never negative" in attenuation_doubt(np.full((4, 4, 4), -500.0))
    assert attenuation_doubt(np.full((4, 4, 4), -0.005)) is None
    assert attenuation_doubt(np.full((4, 4, 4), 1.5)) is not None


def test_i0_help_says_the_normalisation():
    res = run("simulate", "--help")
    text = " ".join(res.output.split())
    assert "I0 exp(-p / max p)" in text and "flat field" not in text
