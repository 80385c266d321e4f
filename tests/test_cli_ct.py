"""clgs simulate / reconstruct / evaluate through click's CliRunner, small volumes."""
import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from clgs.cli import main
from clgs.io.scan import Scan
from clgs.io.volume import load_volume, save_volume

pytest.importorskip("clgs.ct.projector")
pytest.importorskip("clgs.ct.fdk")


def ball_volume(n=24, radius=8.0):
    zz, yy, xx = np.mgrid[:n, :n, :n] - (n - 1) / 2
    vol = np.where(zz ** 2 + yy ** 2 + xx ** 2 < radius ** 2, 0.02, 0.0).astype(np.float32)
    vol[(zz ** 2 + yy ** 2 + xx ** 2) < (radius / 2) ** 2] = 0.01  # a softer core
    return vol


def run(*args, ok=True):
    res = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    if ok:
        assert res.exit_code == 0, res.output
    return res


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    save_volume(d / "ball.nii.gz", ball_volume(), spacing=(2.0, 2.0, 2.0), origin=(-100.0, -50.0, 30.0))
    run("simulate", d / "ball.nii.gz", "--views", 12, "--detector", 32, "--seed", 3, "--surface-level", 0.005,
        "--out", d / "scan")
    return d


def test_simulate_writes_a_complete_scan(scan_dir):
    from clgs.ct.projector import CTProjector

    scan = Scan.load(scan_dir / "scan")
    g = scan.geometry
    assert scan.projections.shape == (12, 32, 32)
    assert g.dVoxel == (2.0, 2.0, 2.0) and g.nVoxel == (24, 24, 24) and g.offOrigin == (0.0, 0.0, 0.0)
    assert np.allclose(g.angles, np.arange(12) * np.pi / 12)
    assert np.array_equal(scan.truth, ball_volume())
    assert scan.meta["acquisition"]["noise"] is True and scan.meta["acquisition"]["seed"] == 3
    assert scan.meta["provenance"]["volume_origin_xyz"] == [-100.0, -50.0, 30.0]
    assert scan.surface is not None and len(scan.surface.faces) > 100
    assert scan.meta["truth_surface_level"] == 0.005
    # the detector sees the whole ball and the noise is noise, not a different signal
    clean = CTProjector(g).forward(scan.truth)
    assert clean[:, 0, :].max() == 0 and clean[:, :, 0].max() == 0  # margins empty
    rel = np.abs(scan.projections - clean).max() / clean.max()
    assert 1e-4 < rel < 0.2


def test_simulate_no_noise_is_the_projector(scan_dir, tmp_path):
    from clgs.ct.projector import CTProjector

    np.save(tmp_path / "ball.npy", ball_volume())
    run("simulate", tmp_path / "ball.npy", "--spacing", "2", "--views", 5, "--arc", 360, "--mode", "parallel",
        "--detector", 40, "--no-noise", "--out", tmp_path / "s")
    scan = Scan.load(tmp_path / "s")
    assert scan.geometry.mode == "parallel"
    assert np.array_equal(scan.projections, CTProjector(scan.geometry).forward(scan.truth))
    assert scan.meta["acquisition"]["noise"] is False


def test_reconstruct_fdk_file_and_folder(scan_dir, tmp_path):
    from clgs import metrics

    res = run("reconstruct", scan_dir / "scan", "--method", "fdk", "--out", tmp_path / "fdk.nii.gz",
              "--json", tmp_path / "fdk.json")
    assert "PSNR" in res.output and "SSIM" in res.output
    vol, sp, org = load_volume(tmp_path / "fdk.nii.gz")
    truth = Scan.load(scan_dir / "scan").truth
    report = json.loads((tmp_path / "fdk.json").read_text())
    assert report["metrics"]["psnr3d"] == pytest.approx(metrics.psnr3d(vol, truth), abs=1e-4)
    assert report["metrics"]["psnr3d"] > 15.0
    assert sp == (2.0, 2.0, 2.0) and org == pytest.approx((-23.0, -23.0, -23.0))
    assert f"{report['metrics']['psnr3d']:.4f}" in res.output
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec", "--filter", "hann")
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["report.json", "volume.nii.gz", "volume.npy"]
    rep = json.loads((tmp_path / "rec" / "report.json").read_text())
    assert rep["method"] == "fdk" and rep["options"] == {"filter": "hann"} and rep["seconds"] > 0
    # existing outputs need --force
    res = run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec", ok=False)
    assert res.exit_code != 0 and "already exists" in res.output and "--force" in res.output
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec", "--force")


def test_reconstruct_sart_options(scan_dir, tmp_path):
    res = run("reconstruct", scan_dir / "scan", "--method", "sart", "--iterations", 2, "--subsets", 3,
              "--out", tmp_path / "sart.npy")
    assert "sart:" in res.output
    vol = np.load(tmp_path / "sart.npy")
    assert vol.shape == (24, 24, 24) and vol.min() >= 0 and vol.max() > 0.005
    res = run("reconstruct", scan_dir / "scan", "--method", "fdk", "--iterations", 3, "--out", tmp_path / "x.npy",
              ok=False)
    assert res.exit_code == 2 and "--iterations" in res.output and "--filter" in res.output
    assert not (tmp_path / "x.npy").exists()
    res = run("reconstruct", scan_dir / "scan", "--method", "nope", "--out", tmp_path / "x.npy", ok=False)
    assert res.exit_code == 2 and "unknown reconstruction method 'nope'" in res.output and "sart" in res.output
    res = run("reconstruct", "--method", "sart", "--help")
    assert "--iterations" in res.output and "--subsets" in res.output and "r2gs" in res.output


def test_evaluate(scan_dir, tmp_path):
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "fdk.nii.gz")
    res = run("evaluate", tmp_path / "fdk.nii.gz", "--truth", scan_dir / "scan", "--level", 0.005,
              "--mask-level", 0.005, "--dilate", 1, "--json", tmp_path / "e.json")
    figures = json.loads((tmp_path / "e.json").read_text())
    assert "surface distance" in res.output and "masked" in res.output
    s = figures["surface"]
    assert 0 < s["mean"] < 2.0 and s["mean"] <= s["p95"] <= s["hausdorff"]  # mm; voxels are 2 mm
    assert figures["mask_voxels"] > (ball_volume() > 0.005).sum()
    # same volume as truth: inf dB (JSON null), SSIM 1, zero surface distance
    save_volume(tmp_path / "t.nii.gz", ball_volume(), spacing=2.0)
    res = run("evaluate", tmp_path / "t.nii.gz", "--truth", tmp_path / "t.nii.gz", "--level", 0.015,
              "--json", tmp_path / "same.json")
    same = json.loads((tmp_path / "same.json").read_text())
    assert same["psnr3d"] is None and same["ssim3d"] == pytest.approx(1.0) and "PSNR inf" in res.output
    assert same["surface"]["hausdorff"] == pytest.approx(0.0, abs=1e-9)
    # a reconstruct output folder is accepted as VOLUME
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec")
    res = run("evaluate", tmp_path / "rec", "--truth", scan_dir / "scan")
    assert f"{figures['psnr3d']:.4f}" in res.output


def test_bad_inputs_give_clear_errors(scan_dir, tmp_path):
    res = run("simulate", tmp_path / "missing.nii.gz", "--out", tmp_path / "s", ok=False)
    assert res.exit_code == 1 and "no such file" in res.output
    np.save(tmp_path / "v.npy", ball_volume())
    res = run("simulate", tmp_path / "v.npy", "--out", tmp_path / "s", ok=False)
    assert res.exit_code == 2 and "--spacing" in res.output
    np.save(tmp_path / "hu.npy", ball_volume() * 1e5 - 1000)
    res = run("simulate", tmp_path / "hu.npy", "--spacing", 1, "--out", tmp_path / "s", ok=False)
    assert "Hounsfield" in res.output
    res = run("simulate", tmp_path / "v.npy", "--spacing", 1, "--out", scan_dir / "scan", ok=False)
    assert "already exists" in res.output
    res = run("simulate", tmp_path / "v.npy", "--spacing", 1, "--DSO", 2000, "--out", tmp_path / "s", ok=False)
    assert res.exit_code == 1 and "DSO" in res.output and "DSD" in res.output
    assert not (tmp_path / "s").exists()

    good = Scan.load(scan_dir / "scan")
    for name, change, message in [
        ("nan", lambda p: p.__setitem__((0, 3, 3), np.nan), "NaN or Inf"),
        ("neg", lambda p: p.__isub__(1.0), "intensities"),
    ]:
        good.save(tmp_path / name)
        p = np.load(tmp_path / name / "projections.npy")
        change(p)
        np.save(tmp_path / name / "projections.npy", p)
        res = run("reconstruct", tmp_path / name, "--out", tmp_path / f"{name}.npy", ok=False)
        assert res.exit_code == 1 and message in res.output, res.output
        assert not (tmp_path / f"{name}.npy").exists()
    good.save(tmp_path / "tiny")
    p = good.projections.copy()
    p[2, 5, 5] = -1e-3 * p.max()
    np.save(tmp_path / "tiny" / "projections.npy", p)
    res = CliRunner().invoke(main, ["reconstruct", str(tmp_path / "tiny"), "--out",
                                     str(tmp_path / "tiny.npy")])
    assert res.exit_code == 0 and "warning: " in res.stderr and "set to 0" in res.stderr
    good.save(tmp_path / "shape")
    np.save(tmp_path / "shape" / "projections.npy", good.projections[:, :, :31])
    res = run("reconstruct", tmp_path / "shape", "--out", tmp_path / "o.npy", ok=False)
    assert "does not match the geometry" in res.output
    res = run("reconstruct", tmp_path / "nowhere", "--out", tmp_path / "o.npy", ok=False)
    assert "no such scan folder" in res.output
    save_volume(tmp_path / "small.nii.gz", np.ones((4, 4, 4)))
    res = run("evaluate", tmp_path / "small.nii.gz", "--truth", scan_dir / "scan", ok=False)
    assert res.exit_code == 2 and "different shapes" in res.output


def test_help_does_not_import_heavy_modules():
    """The three commands' help (and the method list) load neither NumPy nor torch nor OpenCL."""
    code = ("import sys; from click.testing import CliRunner; from clgs.commands import ct; "
            "outs = [CliRunner().invoke(c, ['--help']) for c in (ct.simulate, ct.reconstruct, ct.evaluate)]; "
            "assert all(r.exit_code == 0 for r in outs), [r.output for r in outs]; "
            "assert 'r2gs' in outs[1].output and 'sart' in outs[1].output; "
            "print(sorted(m for m in ('numpy', 'torch', 'pyopencl') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_r2gaussian_folder_reconstructs_like_our_scan(scan_dir, tmp_path):
    from clgs.io.r2gaussian import to_r2gaussian_folder

    to_r2gaussian_folder(Scan.load(scan_dir / "scan"), tmp_path / "r2")
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "ours.npy")
    run("reconstruct", tmp_path / "r2", "--out", tmp_path / "theirs.npy")
    assert np.array_equal(np.load(tmp_path / "ours.npy"), np.load(tmp_path / "theirs.npy"))


# ------------------------------------------------------------------------------ method registry
def _constant(scan, out_dir=None, value=1.0, fail=False, resume=False):
    if fail:
        (out_dir / "partial.txt").write_text("half")
        raise ValueError("diverged")
    if out_dir is not None:
        (out_dir / "extra.txt").write_text(f"resume={resume}")
    return {"volume": np.full(scan.geometry.nVoxel, value, np.float32), "info": {"value": value}}


CONSTANT_OPTIONS = [
    __import__("click").Option(["--value"], type=float, default=None),
    __import__("click").Option(["--fail"], is_flag=True, default=None),
]


def test_registered_methods_run_from_the_cli(scan_dir, tmp_path):
    import click

    from clgs import methods

    methods.register(methods.Method("constant", "tests_helpers_not_imported:never", help="test"), replace=True)
    methods.register(methods.Method("constant", f"{__name__}:_constant", options=f"{__name__}:CONSTANT_OPTIONS",
                                    help="a constant volume"), replace=True)
    with pytest.raises(methods.MethodError, match="already registered"):
        methods.register(methods.Method("constant", _constant))
    assert "constant" in methods.names()
    res = run("reconstruct", scan_dir / "scan", "-m", "constant", "--value", 0.5, "--out", tmp_path / "c")
    assert np.all(np.load(tmp_path / "c" / "volume.npy") == 0.5)
    assert (tmp_path / "c" / "extra.txt").read_text() == "resume=False"
    assert json.loads((tmp_path / "c" / "report.json").read_text())["info"] == {"value": 0.5}
    # a failing method leaves nothing behind (atomic folder)
    res = run("reconstruct", scan_dir / "scan", "-m", "constant", "--fail", "--out", tmp_path / "f", ok=False)
    assert res.exit_code == 1 and "diverged" in res.output
    assert not (tmp_path / "f").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    # a method that manages its own folder may resume into an existing one without --force
    methods.register(methods.Method("resumable", _constant, atomic_dir=False, options=[
        click.Option(["--resume"], is_flag=True, default=None)]), replace=True)
    (tmp_path / "run").mkdir()
    run("reconstruct", scan_dir / "scan", "-m", "resumable", "--resume", "--out", tmp_path / "run")
    assert (tmp_path / "run" / "extra.txt").read_text() == "resume=True"
    res = run("reconstruct", scan_dir / "scan", "-m", "resumable", "--out", tmp_path / "run", ok=False)
    assert "already exists" in res.output
