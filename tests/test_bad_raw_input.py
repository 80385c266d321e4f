"""Raw images that cannot be what clgs import expects: a truncated TIFF among many, HDF5 angles
stored as text, images that hold line integrals or nothing (black) instead of counts. Each ends
in one message naming the file or dataset, or a warning."""
import numpy as np
import pytest
from click.testing import CliRunner

from clgs.cli import main
from clgs.io.raw import RawError, read_raw

N, ROWS, COLS = 12, 3, 32


def _line_integrals():
    """A bar of 1.5 across 9 of 32 columns in every view: 72 % of the pixels see only air (0)."""
    xx = np.arange(COLS)[None, None, :] * np.ones((N, ROWS, 1))
    return np.where(np.abs(xx - 16) < 5, 1.5, 0.0).astype(np.float32)


def _counts():
    return (100.0 + 3e4 * np.exp(-_line_integrals())).astype(np.float32)


def _import(*args):
    return CliRunner().invoke(main, ["import", *map(str, args)])


def test_a_truncated_tiff_in_a_folder_is_named(tmp_path):
    import tifffile

    folder = tmp_path / "proj"
    folder.mkdir()
    for i, im in enumerate(_counts()):
        tifffile.imwrite(folder / f"p{i:03d}.tif", im)
    whole = (folder / "p005.tif").read_bytes()
    (folder / "p005.tif").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(RawError, match="p005.tif: not a readable TIFF, perhaps truncated"):
        read_raw(folder)
    res = _import(folder, "--out", tmp_path / "scan", "--arc", 180)
    assert res.exit_code == 1 and "p005.tif" in res.output and "Traceback" not in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "scan").exists()


def _nxtomo(path, angles):
    import h5py

    with h5py.File(path, "w") as f:
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        det = entry.create_group("instrument").create_group("detector")
        det.attrs["NX_class"] = "NXdetector"
        det["data"] = _counts()
        sample = entry.create_group("sample")
        sample.attrs["NX_class"] = "NXsample"
        sample["rotation_angle"] = angles


def test_angles_stored_as_text_are_named_as_text(tmp_path):
    import h5py

    text = np.array([f"{a:g} deg".encode() for a in np.arange(N) * 15.0])
    with h5py.File(tmp_path / "dx.h5", "w") as f:
        f["exchange/data"] = _counts()
        f["exchange/theta"] = text
    _nxtomo(tmp_path / "nx.nxs", np.array([f"{a:g}" for a in np.arange(N) * 15.0], dtype=h5py.string_dtype()))
    for path, dataset in [(tmp_path / "dx.h5", "exchange/theta"),
                          (tmp_path / "nx.nxs", "/entry/sample/rotation_angle")]:
        with pytest.raises(RawError, match=f"{dataset}: the angles dataset holds text"):
            read_raw(path)
        res = _import(path, "--out", tmp_path / "scan")
        assert res.exit_code == 1, res.output
        assert "holds text" in res.output and dataset in res.output and "not a readable HDF5" not in res.output


def test_images_of_line_integrals_are_warned_and_black_ones_refused(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "li.tif", _line_integrals(), photometric="minisblack")
    res = _import(tmp_path / "li.tif", "--out", tmp_path / "scan", "--arc", 180, "--centre", "middle")
    assert res.exit_code == 0, res.output
    assert "warning:" in res.output and "72% of the pixels are at or below the floor" in res.output
    assert "raw counts?" in res.output and "projections.npy and scan.json" in res.output
    # counts of the same object: no warning
    tifffile.imwrite(tmp_path / "c.tif", _counts(), photometric="minisblack")
    res = _import(tmp_path / "c.tif", "--out", tmp_path / "scan2", "--arc", 180, "--centre", "middle")
    assert res.exit_code == 0 and "at or below the floor" not in res.output, res.output
    # black images with a flat field: every pixel floored
    tifffile.imwrite(tmp_path / "black.tif", np.zeros((N, ROWS, COLS), np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "flat.tif", np.full((2, ROWS, COLS), 3e4, np.float32), photometric="minisblack")
    res = _import(tmp_path / "black.tif", "--flats", tmp_path / "flat.tif", "--out", tmp_path / "scan3", "--arc", 180)
    assert res.exit_code == 1 and "every pixel is at or below the floor" in res.output, res.output
    assert "Traceback" not in res.output and not (tmp_path / "scan3").exists()
