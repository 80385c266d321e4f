"""DICOM series as the standard and a PACS want them: every Type 1 and 2 attribute of the CT Image
IOD's mandatory modules (checked against highdicom's tables of the standard), scanner orientation
with every voxel at its world point (SimpleITK against nibabel), one study and one frame of
reference per scan, identity carried from a DICOM input, the same bytes for the same volume."""
import numpy as np
import pytest
from cli_helpers import run

from clgs.io.units import mu_to_hu
from clgs.io.volume import save_volume

pydicom = pytest.importorskip("pydicom")
sitk = pytest.importorskip("SimpleITK")

ORIGIN = (-120.0, 40.0, 300.0)
SPACING = (3.0, 2.0, 1.5)  # (Z, Y, X)


def files(folder):
    return sorted(folder.glob("*.dcm"))


def read(folder):
    return [pydicom.dcmread(f) for f in files(folder)]


def check_ct_image_iod(ds):
    """Every Type 1 attribute of the CT Image IOD's mandatory modules present with a value, every
    Type 2 present (highdicom's tables, made from the standard), the conditional ones a CT needs,
    and every value valid for its VR (pydicom's checks)."""
    su = pytest.importorskip("highdicom._standard_utils")
    from pydicom import config
    from pydicom.valuerep import validate_value

    assert su.get_sop_class_iod_map()[ds.SOPClassUID] == "ct-image"
    attributes = su.get_module_attribute_map()
    checked = 0
    for module in su.get_iod_module_map()["ct-image"]:
        if module["usage"] != "M":
            continue
        su.check_required_attributes(ds, module["key"])  # highdicom's own check (Type 1 and 2 present)
        for attr in attributes[module["key"]]:
            if attr["path"]:
                continue
            kw, kind = attr["keyword"], attr["type"]
            if kind == "1":
                assert kw in ds and ds[kw].value not in (None, "", b"", []), f"{module['key']}: Type 1 {kw} empty"
                checked += 1
            elif kind == "2":
                assert kw in ds, f"{module['key']}: Type 2 {kw} missing"
                checked += 1
    # conditional attributes a CT image needs: rescale type, patient position, content date/time
    for kw in ("RescaleType", "PatientPosition", "ContentDate", "ContentTime", "SpecificCharacterSet", "PixelData"):
        assert kw in ds, kw
    for elem in ds.iterall():
        if elem.VR != "SQ" and elem.tag != 0x7FE00010:
            if elem.value is None:  # empty (Type 2)
                continue
            values = elem.value if isinstance(elem.value, (list, pydicom.multival.MultiValue)) else [elem.value]
            for v in values:  # the text as stored (DS, IS, PN, DA, TM, UI, CS, ... lengths and characters)
                validate_value(elem.VR, v if isinstance(v, bytes) or type(v) is int else str(v), config.RAISE)
    assert checked > 40
    return checked


@pytest.fixture(scope="module")
def ct(tmp_path_factory):
    d = tmp_path_factory.mktemp("dicomstd")
    mu = np.full((10, 12, 14), 0.019, np.float32)
    mu[3:7, 4:9, 2:6] = 0.045
    mu[2, 1, 12] = 0.08  # one marked voxel: high x, low y
    mu[0] = 0.0
    save_volume(d / "ct.nii.gz", mu, spacing=SPACING, origin=ORIGIN)
    return d, mu


def test_every_slice_meets_the_ct_image_iod(ct, tmp_path):
    d, _ = ct
    run("convert", d / "ct.nii.gz", tmp_path / "s", "--dicom")
    datasets = read(tmp_path / "s")
    assert len(datasets) == 10
    for ds in datasets:
        check_ct_image_iod(ds)
    ds = datasets[0]
    assert ds.file_meta.TransferSyntaxUID == "1.2.840.10008.1.2.1"
    assert str(ds.PatientName) == "ANONYMOUS^CLGS" and ds.PatientID.startswith("CLGS-")
    assert ds.FrameOfReferenceUID.startswith("2.25.") and len(ds.FrameOfReferenceUID) <= 64
    assert ds.RescaleType == "HU" and float(ds.RescaleSlope) == 1 and float(ds.RescaleIntercept) == 0
    assert list(ds.WindowCenterWidthExplanation) == ["DATA", "BONE"]
    assert [float(v) for v in ds.WindowCenter][1] == 400 and [float(v) for v in ds.WindowWidth][1] == 1800
    assert float(ds.WindowWidth[0]) > 0


def test_the_same_volume_gives_the_same_bytes(ct, tmp_path):
    d, _ = ct
    run("convert", d / "ct.nii.gz", tmp_path / "a", "--dicom")
    run("convert", d / "ct.nii.gz", tmp_path / "b", "--dicom")
    fa, fb = files(tmp_path / "a"), files(tmp_path / "b")
    assert [f.name for f in fa] == [f.name for f in fb]
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(fa, fb))
    run("convert", d / "ct.nii.gz", tmp_path / "c", "--dicom", "--kev", 90)  # another energy: another series
    assert pydicom.dcmread(files(tmp_path / "c")[0]).SeriesInstanceUID != pydicom.dcmread(fa[0]).SeriesInstanceUID


def test_orientation_as_scanners_write_it_and_every_voxel_in_place(ct, tmp_path):
    """IOP 1\\0\\0\\0\\1\\0, slices in ascending position; SimpleITK's world point of every voxel
    of the series (LPS) is nibabel's world point (RAS) of the NIfTI voxel with the same value."""
    import nibabel as nib

    d, mu = ct
    run("convert", d / "ct.nii.gz", tmp_path / "s", "--dicom")
    datasets = read(tmp_path / "s")
    zs = [float(ds.ImagePositionPatient[2]) for ds in datasets]
    assert all(list(map(float, ds.ImageOrientationPatient)) == [1, 0, 0, 0, 1, 0] for ds in datasets)
    assert zs == sorted(zs) and np.allclose(np.diff(zs), SPACING[0])
    assert [int(ds.InstanceNumber) for ds in datasets] == list(range(1, 11))
    # pydicom: the marked voxel (x index 12, y index 1) lies at the first pixel's position plus
    # column * dX along +x LPS and row * dY along +y LPS
    ds = datasets[2]
    px = ds.pixel_array
    r, c = np.unravel_index(np.argmax(px), px.shape)
    lps = np.asarray(ds.ImagePositionPatient, float) + c * float(ds.PixelSpacing[1]) * np.array([1, 0, 0]) \
        + r * float(ds.PixelSpacing[0]) * np.array([0, 1, 0])
    ras = lps * [-1, -1, 1]
    assert ras == pytest.approx(np.array(ORIGIN) + np.array([12, 1, 2]) * np.array(SPACING[::-1]))

    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(tmp_path / "s")))
    img = reader.Execute()
    assert img.GetDirection() == pytest.approx((1, 0, 0, 0, 1, 0, 0, 0, 1))
    arr = sitk.GetArrayFromImage(img)  # (z, row, column)
    nii = nib.load(str(d / "ct.nii.gz"))
    data = np.asarray(nii.dataobj)  # (i, j, k) = (x, y, z)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in data.shape], indexing="ij"), -1).reshape(-1, 3)
    world_ras = ijk @ nii.affine[:3, :3].T + nii.affine[:3, 3]
    world_lps = world_ras * [-1, -1, 1]
    index = np.array([img.TransformPhysicalPointToContinuousIndex(tuple(p)) for p in world_lps])
    assert np.abs(index - np.rint(index)).max() < 1e-4  # every NIfTI voxel centre is a DICOM voxel centre
    index = np.rint(index).astype(int)
    got = arr[index[:, 2], index[:, 1], index[:, 0]]
    want = np.rint(mu_to_hu(data[ijk[:, 0], ijk[:, 1], ijk[:, 2]], 70.0))
    np.testing.assert_array_equal(got, want)


@pytest.fixture(scope="module")
def runs(ct, tmp_path_factory):
    """One scan (simulated from a DICOM CT with a patient), reconstructed by FDK and SART."""
    from clgs.io.dicom import save_dicom_series
    from clgs.io.volume import load_volume

    d, _ = ct
    w = tmp_path_factory.mktemp("runs")
    vol, sp, org = load_volume(d / "ct.nii.gz")
    patient = {"PatientName": "Müller^Jöran", "PatientID": "P-0042", "PatientBirthDate": "19700101",
               "PatientSex": "F", "StudyInstanceUID": "1.2.826.0.1.3680043.2.1125.1.42",
               "StudyDate": "20240301", "StudyTime": "101500", "StudyID": "S42", "AccessionNumber": "A42",
               "ReferringPhysicianName": "House^Greg", "FrameOfReferenceUID": "1.2.826.0.1.3680043.2.1125.1.43",
               "PositionReferenceIndicator": "", "PatientPosition": "HFS"}
    save_dicom_series(w / "scanner", vol, sp, org, identity=patient, description="scanner CT")
    run("simulate", w / "scanner", "--hu", "--views", 12, "--detector", 32, "--no-noise", "--out", w / "scan")
    run("simulate", d / "ct.nii.gz", "--views", 12, "--detector", 32, "--no-noise", "--out", w / "anon")
    for method in ("fdk", "sart"):
        extra = ("--iterations", 1) if method == "sart" else ()
        run("reconstruct", w / "scan", "--method", method, "--out", w / method, *extra)
        run("convert", w / method / "volume.nii.gz", w / f"{method}_dcm", "--dicom")
    return w, patient


def test_every_reconstruction_of_a_scan_is_a_series_of_its_study(runs):
    w, patient = runs
    fdk, sart = read(w / "fdk_dcm")[0], read(w / "sart_dcm")[0]
    check_ct_image_iod(fdk)
    assert fdk.StudyInstanceUID == sart.StudyInstanceUID == patient["StudyInstanceUID"]
    assert fdk.FrameOfReferenceUID == sart.FrameOfReferenceUID == patient["FrameOfReferenceUID"]
    assert fdk.SeriesInstanceUID != sart.SeriesInstanceUID
    assert (int(fdk.SeriesNumber), int(sart.SeriesNumber)) == (101, 102)
    assert fdk.SeriesDescription == "clgs FDK, 12 views" and sart.SeriesDescription.startswith("clgs SART")
    assert "sart" in sart.DerivationDescription and "iterations=1" in sart.DerivationDescription
    # the patient came along from the DICOM input
    assert str(fdk.PatientName) == "Müller^Jöran" and fdk.PatientID == "P-0042" and fdk.PatientSex == "F"
    assert (fdk.StudyDate, fdk.StudyTime, fdk.AccessionNumber) == ("20240301", "101500", "A42")
    assert fdk.PatientPosition == "HFS"


def test_a_volume_file_finds_its_study_through_scan_or_report(runs, tmp_path):
    w, patient = runs
    run("reconstruct", w / "anon", "--method", "fdk", "--out", tmp_path / "fdk.nii.gz", "--json",
        tmp_path / "run.json")
    run("reconstruct", w / "anon", "--method", "sart", "--out", tmp_path / "sart", "--iterations", 1)
    run("convert", tmp_path / "fdk.nii.gz", tmp_path / "by_scan", "--dicom", "--scan", w / "anon")
    run("convert", tmp_path / "fdk.nii.gz", tmp_path / "by_report", "--dicom", "--report", tmp_path / "run.json")
    run("convert", tmp_path / "sart" / "volume.nii.gz", tmp_path / "sart_dcm", "--dicom")
    run("convert", w / "anon" / "truth.nii.gz", tmp_path / "truth_dcm", "--dicom")
    a, b = read(tmp_path / "by_scan")[0], read(tmp_path / "by_report")[0]
    s, t = read(tmp_path / "sart_dcm")[0], read(tmp_path / "truth_dcm")[0]
    assert a.StudyInstanceUID == b.StudyInstanceUID == s.StudyInstanceUID == t.StudyInstanceUID
    assert a.FrameOfReferenceUID == s.FrameOfReferenceUID == t.FrameOfReferenceUID
    assert a.StudyInstanceUID != patient["StudyInstanceUID"] and str(a.PatientName) == "ANONYMOUS^CLGS"
    assert len({a.SeriesInstanceUID, s.SeriesInstanceUID, t.SeriesInstanceUID}) == 3
    # the report names the method; a bare --scan does not (series 1, named after the file)
    assert (int(b.SeriesNumber), int(s.SeriesNumber), int(t.SeriesNumber), int(a.SeriesNumber)) == (101, 102, 100, 1)
    assert b.SeriesDescription == "clgs FDK, 12 views" and a.SeriesDescription == "clgs: fdk.nii.gz"
    assert len(a.StudyDate) == 8 and len(a.StudyTime) == 6  # when the scan was made, not now
    # a volume of no scan: its own study and frame, series 1, named after the file
    run("convert", tmp_path / "fdk.nii.gz", tmp_path / "alone", "--dicom", "--series-number", 7)
    alone = read(tmp_path / "alone")[0]
    assert alone.StudyInstanceUID != a.StudyInstanceUID and alone.FrameOfReferenceUID != a.FrameOfReferenceUID
    assert int(alone.SeriesNumber) == 7 and alone.SeriesDescription == "clgs: fdk.nii.gz"
    res = run("convert", tmp_path / "fdk.nii.gz", tmp_path / "x.nii.gz", "--scan", w / "anon", ok=False)
    assert res.exit_code == 2 and "--dicom" in res.output


def test_a_report_whose_scan_is_gone_is_said(runs, tmp_path):
    import json

    w, _ = runs
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "volume.nii.gz").write_bytes((w / "fdk" / "volume.nii.gz").read_bytes())
    (tmp_path / "run" / "report.json").write_text(json.dumps({"method": "fdk", "scan": str(tmp_path / "gone")}))
    res = run("convert", tmp_path / "run" / "volume.nii.gz", tmp_path / "o", "--dicom")
    assert "not there" in res.output and "--scan" in res.output
    assert int(read(tmp_path / "o")[0].SeriesNumber) == 101


def test_to_hu_records_the_unit_in_each_format(ct, tmp_path):
    from clgs.io.units import recorded_units
    from clgs.io.volume import load_volume

    d, mu = ct
    for name in ("hu.nii.gz", "hu.nrrd", "hu.mha"):
        res = run("convert", d / "ct.nii.gz", tmp_path / name, "--to-hu", "--kev", 90)
        assert "Hounsfield units at 90 keV" in res.output
        assert recorded_units(tmp_path / name) == {"units": "HU", "kev": 90.0}, name
        v, sp, org = load_volume(tmp_path / name)
        assert org == pytest.approx(ORIGIN) and sp == pytest.approx(SPACING)
        np.testing.assert_allclose(v, mu_to_hu(mu, 90.0), atol=1e-3)
    run("convert", d / "ct.nii.gz", tmp_path / "mu.nii.gz")
    assert recorded_units(tmp_path / "mu.nii.gz") == {"units": "1/mm"}
    import nibabel as nib

    hdr = nib.load(str(tmp_path / "hu.nii.gz")).header
    assert int(hdr["sform_code"]) == 1 and int(hdr["qform_code"]) == 1
    res = run("convert", d / "ct.nii.gz", tmp_path / "hu.npy", "--to-hu")
    assert "records" in res.output and "bare array" in res.output
