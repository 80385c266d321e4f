"""Atomic writes, the scan folder, NIfTI volumes and meshes."""
import json
import os

import numpy as np
import pytest

from clgs.geometry import Geometry
from clgs.io import atomic
from clgs.io.mesh import MeshError, load_mesh, save_mesh
from clgs.io.scan import Scan, ScanError, ScanWarning, check_projections
from clgs.io.volume import VolumeError, load_volume, save_volume


def small_geometry(n_views=4, mode="cone"):
    return Geometry(DSD=400.0, DSO=250.0, nDetector=(6, 8), dDetector=(1.5, 1.25), nVoxel=(4, 5, 6),
                    dVoxel=(2.0, 1.5, 1.0), offOrigin=(3.0, -2.0, 1.0), offDetector=(0.5, -0.25),
                    angles=np.linspace(0, np.pi, n_views, endpoint=False), mode=mode)


def small_scan(rng, n_views=4, truth=True):
    g = small_geometry(n_views)
    proj = rng.random((n_views, 6, 8)).astype(np.float32)
    vol = rng.random(g.nVoxel).astype(np.float32) if truth else None
    meta = {"acquisition": {"noise": True, "I0": 1e5, "sigma": 10.0, "scatter": 0.0, "seed": 3},
            "subject": "s01", "anatomy": "femur"}
    return Scan(g, proj, vol, meta)


def leftovers(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


# ------------------------------------------------------------------------------ atomic
def test_atomic_file_failure_leaves_old_content(tmp_path):
    target = tmp_path / "a.json"
    atomic.write_json(target, {"x": 1})
    with pytest.raises(RuntimeError), atomic.atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert json.loads(target.read_text()) == {"x": 1}
    assert leftovers(tmp_path) == []
    with pytest.raises(FileExistsError):
        atomic.write_text(target, "new", overwrite=False)


def test_atomic_helpers_roundtrip(tmp_path):
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    atomic.save_npy(tmp_path / "a.data", a)  # no .npy appended
    assert np.array_equal(np.load(tmp_path / "a.data", allow_pickle=False), a)
    atomic.save_npz(tmp_path / "b.npz", x=a, y=np.ones(2))
    with np.load(tmp_path / "b.npz", allow_pickle=False) as z:
        assert np.array_equal(z["x"], a) and z["y"].tolist() == [1, 1]
    with pytest.raises(TypeError):
        atomic.save_npz(tmp_path / "c.npz", x=np.array([{}], dtype=object))
    atomic.write_json(tmp_path / "c.json", {"v": np.float32(1.5), "inf": float("inf"), "arr": np.arange(2)})
    assert json.loads((tmp_path / "c.json").read_text()) == {"v": 1.5, "inf": None, "arr": [0, 1]}


def test_atomic_dir_all_or_nothing(tmp_path):
    target = tmp_path / "out"
    with atomic.atomic_dir(target) as d:
        (d / "one").write_text("1")
    assert (target / "one").read_text() == "1"
    with pytest.raises(FileExistsError), atomic.atomic_dir(target):
        pass
    with pytest.raises(KeyboardInterrupt), atomic.atomic_dir(target, overwrite=True) as d:
        (d / "two").write_text("2")
        raise KeyboardInterrupt
    assert sorted(os.listdir(target)) == ["one"]
    with atomic.atomic_dir(target, overwrite=True) as d:
        (d / "two").write_text("2")
    assert sorted(os.listdir(target)) == ["two"]
    assert leftovers(tmp_path) == []


# ------------------------------------------------------------------------------ scan
def test_scan_roundtrip(tmp_path, rng):
    scan = small_scan(rng)
    scan.save(tmp_path / "s")
    doc = json.loads((tmp_path / "s" / "scan.json").read_text())
    assert doc["format"] == "clgs-scan" and doc["version"] == 1 and "1/mm" in doc["units"]
    back = Scan.load(tmp_path / "s")
    assert back.geometry.to_dict() == scan.geometry.to_dict()
    assert np.array_equal(back.projections, scan.projections)
    assert np.array_equal(back.truth, scan.truth)
    assert back.meta == scan.meta
    # the NIfTI copy of the truth sits where the geometry says
    vol, sp, org = load_volume(tmp_path / "s" / "truth.nii.gz")
    assert np.array_equal(vol, scan.truth)
    assert np.allclose(org, scan.geometry.volume_grid(scene=False).origin)
    with pytest.raises(FileExistsError):
        scan.save(tmp_path / "s")
    scan.subset([0, 2]).save(tmp_path / "s", overwrite=True)
    assert Scan.load(tmp_path / "s").n_views == 2


def test_scan_validation_errors(tmp_path, rng):
    g = small_geometry(3)
    good = rng.random((3, 6, 8)).astype(np.float32)
    with pytest.raises(ScanError, match="does not match the geometry"):
        Scan(g, good[:, :, :7])
    with pytest.raises(ScanError, match="does not match the geometry"):
        Scan(g, good[:2])
    with pytest.raises(ScanError, match="zero views"):
        check_projections(np.zeros((0, 6, 8)), g)
    bad = good.copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(ScanError, match=r"NaN or Inf \(views \[1\]"):
        Scan(g, bad)
    with pytest.raises(ScanError, match="intensities"):
        Scan(g, good - 0.5)
    with pytest.raises(ScanError, match="nVoxel"):
        Scan(g, good, np.zeros((4, 5, 5)))


def test_tiny_negatives_are_clamped_with_warning(rng):
    g = small_geometry(3)
    p = rng.random((3, 6, 8)).astype(np.float32) + 0.5
    p[0, 0, 0] = -0.01  # 1 % of the max: noise
    with pytest.warns(ScanWarning, match="1 slightly negative"):
        s = Scan(g, p)
    assert s.projections.min() == 0.0 and s.projections[0, 0, 0] == 0.0
    assert np.array_equal(s.projections[1:], p[1:])


def test_scan_load_errors(tmp_path, rng):
    with pytest.raises(ScanError, match="no such scan folder"):
        Scan.load(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ScanError, match="neither scan.json"):
        Scan.load(tmp_path / "empty")
    small_scan(rng).save(tmp_path / "s")
    (tmp_path / "s" / "scan.json").write_text("{not json")
    with pytest.raises(ScanError, match="unreadable JSON"):
        Scan.load(tmp_path / "s")
    small_scan(rng).save(tmp_path / "t")
    (tmp_path / "t" / "projections.npy").unlink()
    with pytest.raises(ScanError, match="projections.npy: missing"):
        Scan.load(tmp_path / "t")
    small_scan(rng).save(tmp_path / "u")
    np.save(tmp_path / "u" / "projections.npy", np.ones((4, 8, 6), np.float32))  # V and U swapped
    with pytest.raises(ScanError, match=r"\(4, 8, 6\) does not match the geometry"):
        Scan.load(tmp_path / "u")


@pytest.mark.parametrize("edit,message", [
    (lambda d: d["geometry"].update(DSO="abc"), "DSO must be numbers"),
    (lambda d: d["geometry"].update(nDetector="48x48"), "nDetector must be numbers"),
    (lambda d: d["geometry"].update(nDetector=[6.5, 8]), "nDetector must be whole numbers"),
    (lambda d: d["geometry"].update(nVoxel=[4, float("nan"), 6]), "nVoxel must be whole numbers"),
    (lambda d: d["geometry"].update(angles="abc"), "angles must be numbers"),
    (lambda d: d["geometry"].update(angles=None), "angles are missing"),
    (lambda d: d.update(files=[]), "'files' must map names"),
    (lambda d: d.update(files={"projections": 123}), "'files' must map names"),
    (lambda d: d.update(meta=[1, 2]), "'meta' must be an object"),
    (lambda d: d.update(meta="x"), "'meta' must be an object"),
])
def test_scan_json_with_wrong_types_is_a_scan_error(tmp_path, rng, edit, message):
    small_scan(rng).save(tmp_path / "s")
    doc = json.loads((tmp_path / "s" / "scan.json").read_text())
    edit(doc)
    (tmp_path / "s" / "scan.json").write_text(json.dumps(doc))
    with pytest.raises(ScanError, match=message):
        Scan.load(tmp_path / "s")


def test_files_null_means_the_default_names(tmp_path, rng):
    small_scan(rng).save(tmp_path / "s")
    doc = json.loads((tmp_path / "s" / "scan.json").read_text())
    doc["files"] = None
    (tmp_path / "s" / "scan.json").write_text(json.dumps(doc))
    assert Scan.load(tmp_path / "s").truth is None  # projections.npy found by its default name


def test_complex_or_all_negative_projections_are_refused(rng):
    g = small_geometry(3)
    p = rng.random((3, 6, 8))
    with pytest.raises(ScanError, match="real numbers"):
        check_projections(p + 1j, g)
    with pytest.raises(ScanError, match="every line integral is <= 0"):
        check_projections(-p, g)


# ------------------------------------------------------------------------------ volumes
@pytest.mark.parametrize("suffix", [".nii.gz", ".nii"])
def test_nifti_affine_matches_geometry(tmp_path, rng, suffix):
    import nibabel as nib

    g = small_geometry()
    vol = rng.random(g.nVoxel).astype(np.float32)
    path = save_volume(tmp_path / f"v{suffix}", vol, g)
    img = nib.load(str(path))
    assert img.shape == (6, 5, 4)  # NIfTI order (x, y, z)
    centres = g.volume_grid(scene=False).points()  # (Z, Y, X, 3) world mm, from the Geometry
    for k, j, i in [(0, 0, 0), (3, 4, 5), (1, 2, 3), (3, 0, 5)]:
        world = img.affine @ np.array([i, j, k, 1.0])
        assert np.allclose(world[:3], centres[k, j, i]), (k, j, i)
        expected = np.asarray(g.offOrigin[::-1]) + (np.array([i, j, k]) - (np.array(g.nVoxel[::-1]) - 1) / 2) * \
            np.asarray(g.dVoxel[::-1])
        assert np.allclose(world[:3], expected)
        assert img.get_fdata()[i, j, k] == pytest.approx(vol[k, j, i])
    assert img.header.get_xyzt_units()[0] == "mm"
    back, spacing, origin = load_volume(path)
    assert np.array_equal(back, vol)
    assert np.allclose(spacing, g.dVoxel)
    assert np.allclose(origin, centres[0, 0, 0])


def test_nifti_flipped_file_comes_back_canonical(tmp_path, rng):
    import nibabel as nib

    data_xyz = rng.random((6, 5, 4)).astype(np.float32)
    aff = np.diag([-2.0, 1.5, 3.0, 1.0])
    aff[:3, 3] = [10.0, -4.0, 7.0]
    nib.save(nib.Nifti1Image(data_xyz, aff), str(tmp_path / "lps.nii.gz"))
    vol, sp, org = load_volume(tmp_path / "lps.nii.gz")
    assert sp == pytest.approx((3.0, 1.5, 2.0))
    # x was flipped: voxel i of the file is x = 10 - 2 i; the lowest x is now first
    assert org == pytest.approx((10.0 - 2 * 5, -4.0, 7.0))
    assert np.array_equal(vol[:, :, 0], data_xyz[5].T)


def test_npy_volume_and_errors(tmp_path, rng):
    vol = rng.random((3, 4, 5))
    save_volume(tmp_path / "v.npy", vol)
    back = load_volume(tmp_path / "v.npy")
    assert back.spacing is None and back.origin is None and back.volume.dtype == np.float32
    assert np.allclose(back.volume, vol)
    labels = (vol > 0.5)
    save_volume(tmp_path / "l.nii.gz", labels, spacing=(1, 2, 3))
    lab = load_volume(tmp_path / "l.nii.gz", dtype=None)
    assert lab.volume.dtype == np.uint8 and np.array_equal(lab.volume, labels)
    assert lab.origin == pytest.approx((-6.0, -3.0, -1.0))  # centred by default
    with pytest.raises(VolumeError, match="unknown volume format"):
        save_volume(tmp_path / "v.tif", vol)
    with pytest.raises(VolumeError, match="3-D"):
        save_volume(tmp_path / "v2.npy", vol[0])
    with pytest.raises(VolumeError, match="no such file"):
        load_volume(tmp_path / "missing.nii.gz")
    (tmp_path / "junk.nii.gz").write_bytes(b"not a nifti")
    with pytest.raises(VolumeError, match="not a readable NIfTI"):
        load_volume(tmp_path / "junk.nii.gz")


# ------------------------------------------------------------------------------ meshes
@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj", ".npz"])
def test_mesh_roundtrip(tmp_path, suffix):
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    v = ico.vertices + [1.0, 2.0, 3.0]
    save_mesh(tmp_path / f"m{suffix}", v, ico.faces)
    m = load_mesh(tmp_path / f"m{suffix}")
    assert m.faces.shape == ico.faces.shape and m.vertices.shape == v.shape
    tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
    assert tm.volume == pytest.approx(ico.volume, rel=1e-5)  # same solid, same orientation
    assert np.allclose(tm.centroid, [1, 2, 3], atol=1e-5)


def test_mesh_errors(tmp_path):
    with pytest.raises(MeshError, match="out of range"):
        save_mesh(tmp_path / "m.stl", np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(MeshError, match="unknown mesh format"):
        save_mesh(tmp_path / "m.vtk", np.zeros((3, 3)), [[0, 1, 2]])
    np.savez(tmp_path / "bad.npz", v=np.zeros(3))
    with pytest.raises(MeshError, match="'vertices' and 'faces'"):
        load_mesh(tmp_path / "bad.npz")


def test_a_full_disk_names_the_file_and_leaves_nothing_behind(tmp_path, monkeypatch):
    """ENOSPC while writing: the error names the output and says nothing was replaced; neither a
    temporary file nor a half-made folder is left, and an existing output is kept."""
    import errno

    from clgs.io import atomic

    target = tmp_path / "volume.npy"
    target.write_bytes(b"old")

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(atomic.DiskFullError, match=r"disk is full while writing .*volume\.npy.*nothing was replaced"), \
            atomic.atomic_path(target) as tmp:
        tmp.write_bytes(b"new")
        full()
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["volume.npy"]
    with pytest.raises(atomic.DiskFullError, match="run"), atomic.atomic_dir(tmp_path / "run") as tmp:
        (tmp / "a.txt").write_text("x")
        full()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["volume.npy"]
