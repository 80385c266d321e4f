"""Per-view (vector) geometry from the command line: clgs simulate and clgs femur simulate with
--geometry, clgs import --geometry, and reconstructions of the scans they make."""
import json

import numpy as np
import pytest
from cli_helpers import run

from clgs.geometry import Geometry
from clgs.io.scan import Scan
from clgs.io.volume import save_volume


def c_arm_vectors(n_views=5, arc_deg=120.0, dso=300.0, dsd=450.0, pixel=1.5, offset=(6.0, -4.0), yaw_deg=5.0,
                  centre=(0.0, 0.0, 0.0)):
    """A C-arm-like orbit about ``centre``: views over ``arc_deg``, the source distance and height
    changing per view, the detector offset (u, v mm) and turned about its v axis by ``yaw_deg``."""
    rows = []
    c = np.asarray(centre, float)
    for i, t in enumerate(np.deg2rad(np.linspace(-arc_deg / 2, arc_deg / 2, n_views))):
        e_s = np.array([np.cos(t), np.sin(t), 0.0])
        e_u = np.array([-np.sin(t), np.cos(t), 0.0])
        y = np.deg2rad(yaw_deg)
        u = pixel * (np.cos(y) * e_u - np.sin(y) * e_s)
        src = c + (dso + 5.0 * i) * e_s + np.array([0.0, 0.0, 2.0 * (i - n_views // 2)])
        det = c - (dsd - dso) * e_s + offset[0] * e_u + np.array([0.0, 0.0, offset[1]])
        rows.append([*src, *det, *u, 0.0, 0.0, pixel])
    return rows


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    d = tmp_path_factory.mktemp("vec_cli")
    n = 24
    zz, yy, xx = np.mgrid[:n, :n, :n] - (n - 1) / 2
    vol = np.where(zz ** 2 + yy ** 2 + xx ** 2 < 64, 0.02, 0.0).astype(np.float32)
    save_volume(d / "ball.nii.gz", vol, spacing=(2.0, 2.0, 2.0))
    (d / "carm.json").write_text(json.dumps({"mode": "cone", "nDetector": [40, 48], "vectors": c_arm_vectors()}))
    return d


def test_simulate_from_a_vector_file_and_reconstruct(ball, tmp_path):
    run("simulate", ball / "ball.nii.gz", "--geometry", ball / "carm.json", "--no-noise", "--out", tmp_path / "scan")
    scan = Scan.load(tmp_path / "scan")
    g = scan.geometry
    assert not g.is_circular and g.n_views == 5 and g.nVoxel == (24, 24, 24) and g.dVoxel == (2.0, 2.0, 2.0)
    np.testing.assert_allclose(g.view_vectors(scene=False), c_arm_vectors())
    assert scan.projections.max() > 0.3  # the ball (16 mm across, 0.02/mm) is seen in every view
    assert np.all(scan.projections.reshape(5, -1).max(1) > 0.25)
    # SART reconstructs it
    res = run("reconstruct", tmp_path / "scan", "--method", "sart", "--iterations", 10, "--out", tmp_path / "s.npy")
    vol = np.load(tmp_path / "s.npy")
    truth = scan.truth
    inside, outside = truth > 0, truth == 0
    assert vol[inside].mean() > 0.5 * 0.02 and vol[inside].mean() > 4 * vol[outside].mean()
    # FDK on the views' own geometry: the ball's density comes back on this 5-view, 120-degree arc
    run("reconstruct", tmp_path / "scan", "--method", "fdk", "--out", tmp_path / "f.npy")
    vol = np.load(tmp_path / "f.npy")
    core = np.zeros_like(truth, bool)
    core[9:15, 9:15, 9:15] = True
    assert vol[core].mean() > 0.5 * 0.02 and vol[core].mean() > 4 * np.abs(vol[outside]).mean()
    # R2-Gaussian mode starts from that FDK, and runs
    res = run("reconstruct", tmp_path / "scan", "--method", "r2gs", "--set", "iterations=30",
              "--set", "n_gaussians=2000", "--out", tmp_path / "r")
    vol = np.load(tmp_path / "r" / "volume.npy")
    assert np.isfinite(vol).all() and vol[inside].mean() > 3 * vol[outside].mean()
    # the scanner options make no sense beside a geometry file
    res = run("simulate", ball / "ball.nii.gz", "--geometry", ball / "carm.json", "--views", 7,
              "--out", tmp_path / "x", ok=False)
    assert res.exit_code == 2 and "--views" in res.output


def test_a_tigre_file_gives_the_circular_scan(ball, tmp_path):
    run("simulate", ball / "ball.nii.gz", "--views", 6, "--detector", 32, "--no-noise", "--out", tmp_path / "a")
    a = Scan.load(tmp_path / "a")
    (tmp_path / "tigre.json").write_text(json.dumps(a.geometry.to_dict()))
    run("simulate", ball / "ball.nii.gz", "--geometry", tmp_path / "tigre.json", "--no-noise", "--out", tmp_path / "b")
    b = Scan.load(tmp_path / "b")
    assert b.geometry.is_circular and b.geometry == a.geometry
    np.testing.assert_array_equal(b.projections, a.projections)
    # the same scan written as vectors: the same projections, to float32 rounding
    (tmp_path / "vec.json").write_text(json.dumps(a.geometry.as_vectors().to_dict()))
    run("simulate", ball / "ball.nii.gz", "--geometry", tmp_path / "vec.json", "--no-noise", "--out", tmp_path / "c")
    c = Scan.load(tmp_path / "c")
    assert not c.geometry.is_circular
    np.testing.assert_allclose(c.projections, a.projections, rtol=1e-5, atol=1e-6)


def test_bad_geometry_files_are_clean_errors(ball, tmp_path):
    bad = c_arm_vectors()
    bad[2][5] = float("nan")
    (tmp_path / "nan.json").write_text(json.dumps({"nDetector": [40, 48], "vectors": bad}).replace("NaN", "NaN"))
    res = run("simulate", ball / "ball.nii.gz", "--geometry", tmp_path / "nan.json", "--out", tmp_path / "x", ok=False)
    assert res.exit_code != 0 and "nan.json" in res.output and "view 2" in res.output and "NaN" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "x").exists()
    inside = c_arm_vectors(dso=10.0, dsd=200.0)
    (tmp_path / "inside.json").write_text(json.dumps({"nDetector": [40, 48], "vectors": inside}))
    res = run("simulate", ball / "ball.nii.gz", "--geometry", tmp_path / "inside.json", "--out", tmp_path / "x",
              ok=False)
    assert res.exit_code != 0 and "view 0" in res.output and "inside the volume" in res.output


def test_import_takes_a_vector_geometry_file(tmp_path):
    rng = np.random.default_rng(0)
    counts = rng.uniform(800, 1000, size=(5, 40, 48)).astype(np.float32)
    np.save(tmp_path / "raw.npy", counts)
    np.save(tmp_path / "flat.npy", np.full((40, 48), 1000.0, np.float32))
    geo = {"mode": "cone", "nDetector": [40, 48], "nVoxel": [24, 24, 24], "dVoxel": [2.0, 2.0, 2.0],
           "vectors": c_arm_vectors()}
    (tmp_path / "geo.json").write_text(json.dumps(geo))
    # random counts on every pixel are a detector without structure, all of it as flat as air: the
    # beam normalisation would take it all as air, so it is off here (the counts are the truth)
    res = run("import", tmp_path / "raw.npy", "--flats", tmp_path / "flat.npy", "--geometry", tmp_path / "geo.json",
              "--air-columns", "off", "--out", tmp_path / "scan")
    assert "per-view vectors" in res.output
    scan = Scan.load(tmp_path / "scan")
    np.testing.assert_allclose(scan.geometry.view_vectors(scene=False), c_arm_vectors())
    np.testing.assert_allclose(scan.projections, -np.log(counts / 1000.0), rtol=1e-5, atol=1e-6)
    # a view count that differs from the images names the file and both counts
    geo["vectors"] = geo["vectors"][:4]
    (tmp_path / "four.json").write_text(json.dumps(geo))
    res = run("import", tmp_path / "raw.npy", "--flats", tmp_path / "flat.npy", "--geometry", tmp_path / "four.json",
              "--out", tmp_path / "x", ok=False)
    assert res.exit_code != 0 and "four.json" in res.output
    assert "4 views" in res.output and "5 projections" in res.output
    # so does a detector of another size
    geo["vectors"] = c_arm_vectors()
    geo["nDetector"] = [40, 50]
    (tmp_path / "wide.json").write_text(json.dumps(geo))
    res = run("import", tmp_path / "raw.npy", "--flats", tmp_path / "flat.npy", "--geometry", tmp_path / "wide.json",
              "--out", tmp_path / "x", ok=False)
    assert res.exit_code != 0 and "wide.json" in res.output and "[40, 50]" in res.output


def _has_femur():
    try:
        from clgs.anatomy import plugins

        return "femur" in plugins.anatomy_names()
    except Exception:  # noqa: BLE001
        return False


@pytest.mark.skipif(not _has_femur(), reason="install with: pip install -e anatomies/femur")
def test_femur_c_arm_scan_simulates_and_reconstructs_with_the_shape_method(tmp_path):
    """5 views over 120 degrees, the detector offset, turned and rolled (the voxel projector's upright
    stand-in): simulate, then a short shape-guided run."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "c_arm_geometry.py"
    r = subprocess.run([sys.executable, str(script), "--roll", "3", "--out", str(tmp_path / "carm.json")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "carm.json").read_text())["vectors"]
    g = Geometry.from_dict({"nDetector": [200, 160], "nVoxel": [8, 8, 8], "dVoxel": [1, 1, 1], "vectors": rows})
    assert np.degrees(g.angles.max() - g.angles.min()) == pytest.approx(120.0)
    assert np.ptp(np.linalg.norm(g.view_vectors(scene=False)[:, :3], axis=1)) > 50  # the source distance varies
    assert np.all(np.abs(g.view_vectors(scene=False)[:, 8]) > 0.1)  # rolled: u has a z part
    res = run("femur", "simulate", "--geometry", tmp_path / "carm.json", "--out", tmp_path / "scan")
    assert "5 views from" in res.output
    scan = Scan.load(tmp_path / "scan")
    assert not scan.geometry.is_circular and scan.projections.shape == (5, 200, 160)
    np.testing.assert_allclose(scan.geometry.view_vectors(scene=False), rows)
    res = run("femur", "simulate", "--geometry", tmp_path / "carm.json", "--arc", 90, "--out", tmp_path / "x", ok=False)
    assert res.exit_code == 2 and "--arc" in res.output
    res = run("femur", "reconstruct", tmp_path / "scan", "--method", "shape", "--out", tmp_path / "rec",
              "--set", "iterations=20", "--set", "n_shape=3000", "--set", "n_free=1000",
              "--set", "alpha_init_iterations=5")
    assert "shape reconstruction of 5 views" in res.output
    vol = np.load(tmp_path / "rec" / "volume.npy")
    assert vol.shape == scan.truth.shape and np.isfinite(vol).all()
    assert float(np.corrcoef(vol.ravel(), scan.truth.ravel())[0, 1]) > 0.5
