"""Volumes in the formats imaging people use (NIfTI, MetaImage, NRRD, DICOM series) keep their
place in the world; Hounsfield units convert at a stated energy; meshes declare their frame."""

import nibabel as nib
import numpy as np
import pytest

from clgs.io.mesh import load_mesh, mesh_space, save_mesh
from clgs.io.units import UnitsError, hu_to_mu, mu_to_hu, water_mu
from clgs.io.volume import VolumeError, load_volume, save_volume

sitk = pytest.importorskip("SimpleITK", reason="the formats extra (SimpleITK) is part of the set-up")

SPACING = (2.0, 1.5, 1.25)  # dZ, dY, dX
ORIGIN = (-120.0, 40.0, 300.0)  # x, y, z of voxel [0, 0, 0]
VOXEL = (1, 2, 3)  # k, j, i


def _volume():
    return np.random.default_rng(0).random((4, 5, 6)).astype(np.float32)


def _world_ras(path, kji):
    """World (RAS, mm) centre of voxel [k, j, i], read by the format's own library."""
    k, j, i = kji
    if str(path).endswith((".nii", ".nii.gz")):
        return (nib.load(str(path)).affine @ [i, j, k, 1.0])[:3]
    img = sitk.ReadImage(str(path))
    return np.asarray(img.TransformIndexToPhysicalPoint((i, j, k))) * [-1, -1, 1]  # LPS -> RAS


@pytest.mark.parametrize("name", ["v.nii.gz", "v.nii", "v.mha", "v.mhd", "v.nrrd", "v.nhdr"])
def test_round_trip_keeps_values_and_world_position(tmp_path, name):
    vol = _volume()
    path = save_volume(tmp_path / name, vol, spacing=SPACING, origin=ORIGIN)
    got = load_volume(path)
    assert np.array_equal(got.volume, vol)
    assert np.allclose(got.spacing, SPACING) and np.allclose(got.origin, ORIGIN)
    k, j, i = VOXEL
    want = np.asarray(ORIGIN) + np.array([i, j, k]) * np.asarray(SPACING)[::-1]
    assert np.allclose(_world_ras(path, VOXEL), want, atol=1e-6)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind


def _write_dicom_series(folder, hu, spacing, origin_lps):
    """One CT slice a file, as a scanner writes them (int16 HU, positions in LPS)."""
    folder.mkdir()
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(hu.shape[0]):
        sl = sitk.GetImageFromArray(hu[k].astype(np.int16))
        pos = (origin_lps[0], origin_lps[1], origin_lps[2] + k * spacing[0])
        for tag, value in [("0008|0060", "CT"), ("0008|0016", "1.2.840.10008.5.1.4.1.1.2"),
                           ("0020|000d", "1.2.826.0.1.3680043.2.1125.1"), ("0020|000e", "1.2.826.0.1.3680043.2.1125.2"),
                           ("0020|0032", "\\".join(f"{v:g}" for v in pos)), ("0020|0037", "1\\0\\0\\0\\1\\0"),
                           ("0028|0030", f"{spacing[1]:g}\\{spacing[2]:g}"), ("0018|0050", f"{spacing[0]:g}"),
                           ("0020|0013", str(k + 1)), ("0008|0018", f"1.2.826.0.1.3680043.2.1125.3.{k + 1}")]:
            sl.SetMetaData(tag, value)
        sl.SetSpacing((spacing[2], spacing[1]))
        writer.SetFileName(str(folder / f"slice{k:03d}.dcm"))
        writer.Execute(sl)


def test_dicom_series_is_read_with_its_position(tmp_path):
    hu = np.round(np.random.default_rng(1).uniform(-1000, 1500, (5, 6, 7)))
    spacing, origin_lps = (2.5, 0.75, 0.75), (100.0, -60.0, -200.0)
    _write_dicom_series(tmp_path / "ct", hu, spacing, origin_lps)
    for where in (tmp_path / "ct", tmp_path / "ct" / "slice002.dcm"):
        got = load_volume(where, dtype=None)
        # the DICOM columns and rows run along LPS +x and +y, i.e. RAS -x and -y: the array comes
        # back reversed along x and y, and its first voxel is the series' far corner, in RAS
        assert np.array_equal(got.volume, hu.astype(np.int16)[:, ::-1, ::-1])
        assert np.allclose(got.spacing, spacing)
        far_lps = np.asarray(origin_lps) + [6 * 0.75, 5 * 0.75, 0.0]
        assert np.allclose(got.origin, far_lps * [-1, -1, 1])


def test_dicom_ct_in_hounsfield_units_simulates_with_hu(tmp_path):
    from click.testing import CliRunner

    from clgs.cli import main
    from clgs.io.scan import Scan

    hu = np.full((6, 8, 8), -1000.0)
    hu[1:5, 2:6, 2:6] = 700.0  # bone-like block in air
    _write_dicom_series(tmp_path / "ct", hu, (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    args = ["simulate", str(tmp_path / "ct"), "--out", str(tmp_path / "scan"), "--views", "3", "--detector", "16",
            "--no-noise"]
    refused = CliRunner().invoke(main, args)
    assert refused.exit_code != 0 and "--hu" in refused.output
    res = CliRunner().invoke(main, args + ["--hu", "--kev", "60"])
    assert res.exit_code == 0, res.output
    truth = Scan.load(tmp_path / "scan").truth
    assert truth.max() == pytest.approx(0.02059 * 1.7, rel=1e-5) and truth.min() == 0.0


def test_hounsfield_round_trip_and_energy_table():
    hu = np.linspace(-1000, 3000, 101)
    assert np.abs(mu_to_hu(hu_to_mu(hu, 70), 70) - hu).max() < 0.5
    assert water_mu(60) == pytest.approx(0.02059) and 0.01837 < water_mu(70) < 0.02059
    assert hu_to_mu([-1200.0])[0] == 0.0  # below air: clipped, never negative attenuation
    with pytest.raises(UnitsError, match="outside"):
        water_mu(20)
    with pytest.raises(UnitsError, match="NaN"):
        hu_to_mu([np.nan])


def test_integer_labels_are_stored_in_a_type_nifti_takes(tmp_path):
    labels = np.arange(60, dtype=np.int64).reshape(3, 4, 5)
    got = load_volume(save_volume(tmp_path / "l.nii.gz", labels), dtype=None).volume
    assert got.dtype == np.uint8 and np.array_equal(got, labels)
    wide = labels * 100_000
    assert load_volume(save_volume(tmp_path / "w.nii.gz", wide), dtype=None).volume.dtype == np.int32
    with pytest.raises(VolumeError, match="32 bits"):
        save_volume(tmp_path / "x.nii.gz", labels * 2**40)
    with pytest.raises(VolumeError, match="complex"):
        save_volume(tmp_path / "c.nii.gz", labels.astype(complex))


def test_oblique_volume_is_resampled_in_place_with_a_warning(tmp_path):
    c, s = np.cos(0.4), np.sin(0.4)
    aff = np.eye(4)
    aff[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    aff[:3, 3] = [10.0, 20.0, 30.0]
    data = np.zeros((9, 9, 5), np.float32)
    data[3:6, 3:6, 1:4] = 1.0  # a block around voxel (4, 4, 2)
    nib.save(nib.Nifti1Image(data, aff), str(tmp_path / "o.nii.gz"))
    with pytest.warns(UserWarning, match="oblique.*resampled"):
        got = load_volume(tmp_path / "o.nii.gz")
    centre_world = (aff @ [4, 4, 2, 1])[:3]
    idx = np.round((centre_world - np.asarray(got.origin)) / np.asarray(got.spacing)[::-1]).astype(int)
    assert got.volume[idx[2], idx[1], idx[0]] == pytest.approx(1.0)
    assert got.volume.sum() == pytest.approx(data.sum(), rel=0.2)


def test_zero_voxel_size_is_refused(tmp_path):
    img = nib.Nifti1Image(np.ones((3, 3, 3), np.float32), None)
    img.header.set_zooms((1.0, 0.0, 1.0))  # no sform/qform: the voxel sizes alone place it
    nib.save(img, str(tmp_path / "z.nii.gz"))
    with pytest.raises(VolumeError, match="degenerate|zero"):
        load_volume(tmp_path / "z.nii.gz")


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj"])
def test_meshes_are_written_in_lps_with_the_tag_slicer_reads(tmp_path, suffix):
    import trimesh

    sphere = trimesh.creation.icosphere(1)
    vertices = sphere.vertices * 10 + [100.0, -50.0, 30.0]
    path = save_mesh(tmp_path / f"m{suffix}", vertices, sphere.faces)
    assert mesh_space(path) == "LPS"
    raw = trimesh.load(str(path), force="mesh", process=False)
    assert np.allclose(np.asarray(raw.vertices).mean(0), [-100.0, 50.0, 30.0], atol=1e-3)
    back = load_mesh(path)
    assert np.allclose(back.vertices.mean(0), vertices.mean(0), atol=1e-3)


def test_ras_tagged_meshes_are_read_as_ras_and_untagged_ones_as_asked(tmp_path):
    import trimesh

    from clgs.io.mesh import MeshWarning

    sphere = trimesh.creation.icosphere(1)
    vertices = sphere.vertices + [5.0, 6.0, 7.0]
    tm = trimesh.Trimesh(vertices, sphere.faces, process=False)
    (tmp_path / "plain.obj").write_text(tm.export(file_type="obj"))
    (tmp_path / "ras.obj").write_text("# SPACE=RAS\n" + tm.export(file_type="obj"))
    assert np.allclose(load_mesh(tmp_path / "ras.obj").vertices.mean(0), [5.0, 6.0, 7.0], atol=1e-6)
    assert np.allclose(load_mesh(tmp_path / "plain.obj", space="RAS").vertices.mean(0), [5.0, 6.0, 7.0], atol=1e-6)
    with pytest.warns(MeshWarning, match="read as LPS"):
        assert np.allclose(load_mesh(tmp_path / "plain.obj").vertices.mean(0), [-5.0, -6.0, 7.0], atol=1e-6)
    assert mesh_space(tmp_path / "plain.obj") is None and mesh_space(tmp_path / "ras.obj") == "RAS"
