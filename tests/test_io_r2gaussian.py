"""R2-Gaussian dataset folders: handcrafted folders laid out as their generator writes them, our
writer, and the camera-model facts behind the flip."""
import json

import numpy as np
import pytest

from clgs.geometry import Geometry
from clgs.io.r2gaussian import geometry_from_scanner, to_r2gaussian_folder
from clgs.io.scan import Scan, ScanError, read_r2gaussian


def handcrafted(folder, rng, n_train=3, n_test=2, vol_key="vol", dvoxel=False):
    """A folder as R2-Gaussian's synthetic generator lays it out: [x, y, z] volume, per-view (V, U)
    images (rows top-down), [x, y, z] voxel fields, [u, v] detector offset, sizes not spacings."""
    nx, ny, nz = 6, 5, 4
    scanner = {
        "mode": "cone", "filter": None, "DSD": 7.0, "DSO": 5.0,
        "nDetector": [7, 9], "sDetector": [3.5, 4.5],  # [V, U]
        "nVoxel": [nx, ny, nz], "sVoxel": [1.2, 1.0, 0.8],  # [x, y, z]
        "offOrigin": [0.1, -0.2, 0.3], "offDetector": [0.05, -0.15],  # [x, y, z], [u, v]
        "accuracy": 0.5, "totalAngle": 180.0, "startAngle": 0.0,
        "noise": True, "possion_noise": 10000, "gaussian_noise": [0, 10],
    }
    if dvoxel:
        scanner["dVoxel"] = [0.2, 0.2, 0.2]
    vol = rng.random((nx, ny, nz)).astype(np.float32)
    folder.mkdir()
    np.save(folder / "vol_gt.npy", vol)
    meta = {"scanner": scanner, vol_key: "vol_gt.npy", "bbox": [[-1, -1, -1], [1, 1, 1]]}
    images = {}
    for split, n in (("proj_train", n_train), ("proj_test", n_test)):
        (folder / split).mkdir()
        meta[split] = []
        angles = np.linspace(0, np.pi, n, endpoint=False) + (0.3 if split == "proj_test" else 0.0)
        images[split] = rng.random((n, 7, 9)).astype(np.float32)
        for i in range(n):
            name = f"{split}/{split}_{i:04d}.npy"
            np.save(folder / name, images[split][i])
            meta[split].append({"file_path": name, "angle": float(angles[i])})
    (folder / "meta_data.json").write_text(json.dumps(meta, indent=4))
    return vol, images, meta


def test_handcrafted_folder_axes_and_flip(tmp_path, rng):
    vol, images, meta = handcrafted(tmp_path / "case", rng)
    scan = Scan.load(tmp_path / "case")  # detects the R2-Gaussian layout
    g = scan.geometry
    assert g.nVoxel == (4, 5, 6)  # their [x, y, z] reversed
    assert g.dVoxel == pytest.approx((0.2, 0.2, 0.2))  # sVoxel / nVoxel
    assert g.offOrigin == pytest.approx((0.3, -0.2, 0.1))
    assert g.nDetector == (7, 9) and g.dDetector == pytest.approx((0.5, 0.5))
    assert g.offDetector == pytest.approx((-0.15, 0.05))  # their [u, v] -> our (V, U)
    assert np.allclose(g.angles, [m["angle"] for m in meta["proj_train"]])
    for i, j, k in [(0, 0, 0), (5, 4, 3), (2, 1, 3)]:
        assert scan.truth[k, j, i] == vol[i, j, k]
    for n in range(3):
        for iv in range(7):
            assert np.array_equal(scan.projections[n, iv], images["proj_train"][n, 6 - iv])
    assert scan.meta["acquisition"] == {"noise": True, "I0": 10000, "sigma": 10}
    test = read_r2gaussian(tmp_path / "case", split="test")
    assert test.n_views == 2 and np.array_equal(test.projections[1], images["proj_test"][1][::-1])


def test_real_data_layout_ct_key_and_dvoxel(tmp_path, rng):
    vol, _, _ = handcrafted(tmp_path / "real", rng, vol_key="ct", dvoxel=True)
    scan = Scan.load(tmp_path / "real" / "meta_data.json")
    assert np.array_equal(scan.truth, vol.transpose(2, 1, 0))


def test_roundtrip_through_our_writer(tmp_path, rng):
    vol, images, _ = handcrafted(tmp_path / "case", rng)
    train = Scan.load(tmp_path / "case")
    test = read_r2gaussian(tmp_path / "case", split="test")
    to_r2gaussian_folder(train, tmp_path / "again", test=test)
    # same arrays, file by file, in their layout
    meta = json.loads((tmp_path / "again" / "meta_data.json").read_text())
    assert np.array_equal(np.load(tmp_path / "again" / meta["vol"]), vol)
    for split in ("proj_train", "proj_test"):
        for i, e in enumerate(meta[split]):
            assert np.array_equal(np.load(tmp_path / "again" / e["file_path"]), images[split][i])
    sc = meta["scanner"]
    assert sc["nVoxel"] == [6, 5, 4] and sc["offDetector"] == pytest.approx([0.05, -0.15])
    assert sc["offOrigin"] == pytest.approx([0.1, -0.2, 0.3]) and sc["sDetector"] == pytest.approx([3.5, 4.5])
    back = Scan.load(tmp_path / "again")
    assert back.geometry.to_dict() == train.geometry.to_dict()
    assert np.array_equal(back.projections, train.projections) and np.array_equal(back.truth, train.truth)


def test_our_scan_to_r2gaussian_and_back(tmp_path, rng):
    g = Geometry(DSD=1500, DSO=1000, nDetector=(8, 10), dDetector=(1.0, 1.2), nVoxel=(3, 4, 5),
                 dVoxel=(1.0, 2.0, 3.0), angles=np.linspace(0, np.pi, 5, endpoint=False), mode="parallel",
                 offOrigin=(1, 2, 3), offDetector=(0.5, 0.25))
    scan = Scan(g, rng.random((5, 8, 10)).astype(np.float32), rng.random((3, 4, 5)).astype(np.float32),
                {"acquisition": {"noise": True, "I0": 1e5, "sigma": 10.0}})
    to_r2gaussian_folder(scan, tmp_path / "r2")
    sc = json.loads((tmp_path / "r2" / "meta_data.json").read_text())["scanner"]
    assert sc["totalAngle"] == pytest.approx(180.0) and sc["startAngle"] == 0.0
    assert sc["possion_noise"] == 1e5 and sc["gaussian_noise"] == [0.0, 10.0]
    back = Scan.load(tmp_path / "r2")
    assert back.geometry.to_dict() == g.to_dict()
    assert np.array_equal(back.projections, scan.projections) and np.array_equal(back.truth, scan.truth)
    with pytest.raises(FileExistsError):
        to_r2gaussian_folder(scan, tmp_path / "r2")


def test_flip_matches_their_camera_model(rng):
    """R2-Gaussian's camera (from its angle2pose): centre DSO (cos a, sin a, 0), image x axis
    (-sin a, cos a, 0), image y axis (0, 0, -1), pinhole at DSD with the principal point at the
    image centre. A point must land on their image pixel (row r, column c) exactly where our
    geometry's ray through detector pixel (V-1-r, c) passes."""
    V, U, du, dv = 7, 9, 0.5, 0.4
    scanner = {"mode": "cone", "DSD": 7.0, "DSO": 5.0, "nDetector": [V, U], "dDetector": [dv, du],
               "nVoxel": [4, 4, 4], "sVoxel": [2, 2, 2]}
    for a in rng.uniform(0, 2 * np.pi, 4):
        g = geometry_from_scanner(scanner, [a])
        src, dirs = g.rays(0, scene=False)
        p = rng.uniform(-0.8, 0.8, 3)
        c_cam = 5.0 * np.array([np.cos(a), np.sin(a), 0])
        x_ax, y_ax = np.array([-np.sin(a), np.cos(a), 0]), np.array([0, 0, -1.0])
        z_ax = np.cross(x_ax, y_ax)  # viewing direction, towards the axis
        assert np.allclose(z_ax, -c_cam / 5.0)
        q = p - c_cam
        col = 7.0 * (q @ x_ax) / (q @ z_ax) / du + (U - 1) / 2
        row = 7.0 * (q @ y_ax) / (q @ z_ax) / dv + (V - 1) / 2
        iv, iu = (V - 1) - row, col  # our detector coordinates after the flip
        # the ray of our geometry through fractional pixel (iv, iu) passes through p
        vec = g.view_vectors(scene=False)[0]
        pix = vec[3:6] + (iu - (U - 1) / 2) * vec[6:9] + (iv - (V - 1) / 2) * vec[9:12]
        d = pix - vec[0:3]
        d /= np.linalg.norm(d)
        off = (p - vec[0:3]) - ((p - vec[0:3]) @ d) * d
        assert np.linalg.norm(off) < 1e-9
        assert np.allclose(src[0, 0], vec[0:3])


def test_bad_folders(tmp_path, rng):
    handcrafted(tmp_path / "a", rng)
    meta = json.loads((tmp_path / "a" / "meta_data.json").read_text())
    meta["proj_train"] = []
    (tmp_path / "a" / "meta_data.json").write_text(json.dumps(meta))
    with pytest.raises(ScanError, match="zero views"):
        Scan.load(tmp_path / "a")
    handcrafted(tmp_path / "b", rng)
    np.save(tmp_path / "b" / "proj_train" / "proj_train_0001.npy", np.zeros((9, 7), np.float32))
    with pytest.raises(ScanError, match=r"shape \(9, 7\) does not match"):
        Scan.load(tmp_path / "b")
    handcrafted(tmp_path / "c", rng)
    np.save(tmp_path / "c" / "vol_gt.npy", np.zeros((4, 5, 6), np.float32))  # (Z,Y,X) instead of [x,y,z]
    with pytest.raises(ScanError, match=r"nVoxel \[x, y, z\] = \[6, 5, 4\]"):
        Scan.load(tmp_path / "c")
    handcrafted(tmp_path / "d", rng)
    (tmp_path / "d" / "proj_train" / "proj_train_0000.npy").unlink()
    with pytest.raises(ScanError, match="proj_train_0000.npy: missing"):
        Scan.load(tmp_path / "d")
    handcrafted(tmp_path / "e", rng)
    meta = json.loads((tmp_path / "e" / "meta_data.json").read_text())
    del meta["scanner"]["DSO"]
    (tmp_path / "e" / "meta_data.json").write_text(json.dumps(meta))
    with pytest.raises(ScanError, match="missing DSO"):
        Scan.load(tmp_path / "e")


@pytest.mark.parametrize("key,value,message", [("DSD", "abc", "DSD must be numbers"),
                                               ("nDetector", [float("nan"), 8], "whole numbers"),
                                               ("nVoxel", [4, 4.5, 4], "whole numbers")])
def test_scanner_values_of_the_wrong_kind_are_scan_errors(key, value, message):
    from clgs.io.scan import ScanError

    scanner = {"DSD": 1500.0, "DSO": 1000.0, "nDetector": [6, 8], "dDetector": [1.0, 1.0],
               "nVoxel": [4, 4, 4], "dVoxel": [1.0, 1.0, 1.0], "mode": "cone", key: value}
    with pytest.raises(ScanError, match=message):
        geometry_from_scanner(scanner, [0.0, 1.0])
