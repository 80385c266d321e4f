"""DICOM folders that are not one evenly spaced series: two series in one folder (volumes and
projections), a series with missing slices, a single slice with its SliceThickness."""
import numpy as np
import pytest
from click.testing import CliRunner

from clgs.cli import main
from clgs.io.raw import RawError, read_raw
from clgs.io.volume import VolumeError, load_volume

sitk = pytest.importorskip("SimpleITK")
pytest.importorskip("pydicom")


def _write(folder, images, series_uid, description, z_positions=None, thickness=2.0, first=0):
    """One image a file, as a scanner writes them (int16, positions in LPS along z)."""
    folder.mkdir(exist_ok=True)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k, im in enumerate(images):
        z = k * thickness if z_positions is None else z_positions[k]
        sl = sitk.GetImageFromArray(np.asarray(im, np.int16))
        for tag, value in [("0008|0060", "CT"), ("0008|0016", "1.2.840.10008.5.1.4.1.1.2"),
                           ("0020|000d", "1.2.826.0.1.3680043.2.1125.1"), ("0020|000e", series_uid),
                           ("0008|103e", description), ("0020|0011", series_uid[-1]),
                           ("0020|0032", f"0\\0\\{z:g}"), ("0020|0037", "1\\0\\0\\0\\1\\0"),
                           ("0028|0030", "1\\1"), ("0018|0050", f"{thickness:g}"), ("0020|0013", str(k + 1)),
                           ("0008|0018", f"{series_uid}.{k + 1}")]:
            sl.SetMetaData(tag, value)
        sl.SetSpacing((1.0, 1.0))
        writer.SetFileName(str(folder / f"im{first + k:03d}.dcm"))
        writer.Execute(sl)


def test_a_folder_of_two_series_is_refused_naming_both(tmp_path):
    images = np.full((4, 6, 8), 100)
    _write(tmp_path / "ct", images, "1.2.826.0.1.3680043.2.1125.7", "AXIAL 2mm")
    _write(tmp_path / "ct", images[:3], "1.2.826.0.1.3680043.2.1125.8", "SCOUT", first=10)
    with pytest.raises(VolumeError, match=r"2 DICOM series.*'AXIAL 2mm' \(series 7, 4 files.*'SCOUT'.*3 files"):
        load_volume(tmp_path / "ct")
    res = CliRunner().invoke(main, ["simulate", str(tmp_path / "ct"), "--out", str(tmp_path / "scan")])
    assert res.exit_code == 1 and "'SCOUT'" in res.output and "subfolder" in res.output, res.output
    assert "Traceback" not in res.output
    # projection images: refused too, never stacked as one acquisition
    with pytest.raises(RawError, match=r"2 DICOM series.*AXIAL 2mm.*1\.2\.826\.0\.1\.3680043\.2\.1125\.8.*subfolder"):
        read_raw(tmp_path / "ct")
    res = CliRunner().invoke(main, ["import", str(tmp_path / "ct"), "--out", str(tmp_path / "s2"), "--arc", "180"])
    assert res.exit_code == 1 and "'SCOUT'" in res.output and "Traceback" not in res.output, res.output


def test_missing_slices_are_named_and_a_single_slice_keeps_its_thickness(tmp_path):
    images = np.full((5, 6, 8), 100)
    _write(tmp_path / "gap", images, "1.2.826.0.1.3680043.2.1125.9", "GAP",
           z_positions=[0.0, 2.0, 4.0, 10.0, 12.0])
    with pytest.warns(UserWarning, match=r"4 to 10 mm \(about 2 slices missing\)"):
        load_volume(tmp_path / "gap")
    _write(tmp_path / "one", images[:1], "1.2.826.0.1.3680043.2.1125.9", "ONE", thickness=1.5)
    for path in (tmp_path / "one", tmp_path / "one" / "im000.dcm"):
        assert load_volume(path).spacing == pytest.approx((1.5, 1.0, 1.0))
