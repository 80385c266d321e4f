"""clgs simulate / reconstruct / evaluate through click's CliRunner, small volumes."""
import json
import signal
import subprocess
import sys

import numpy as np
import pytest
from cli_helpers import run
from click.testing import CliRunner

from clgs.cli import main
from clgs.io.scan import Scan
from clgs.io.volume import load_volume, save_volume

pytest.importorskip("clgs.ops.ct_projector")
pytest.importorskip("clgs.ct.fdk")


def ball_volume(n=24, radius=8.0):
    zz, yy, xx = np.mgrid[:n, :n, :n] - (n - 1) / 2
    vol = np.where(zz ** 2 + yy ** 2 + xx ** 2 < radius ** 2, 0.02, 0.0).astype(np.float32)
    vol[(zz ** 2 + yy ** 2 + xx ** 2) < (radius / 2) ** 2] = 0.01  # a softer core
    return vol




@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    save_volume(d / "ball.nii.gz", ball_volume(), spacing=(2.0, 2.0, 2.0), origin=(-100.0, -50.0, 30.0))
    run("simulate", d / "ball.nii.gz", "--views", 12, "--detector", 32, "--seed", 3, "--surface-level", 0.005,
        "--out", d / "scan")
    return d


def test_simulate_writes_a_complete_scan(scan_dir):
    from clgs.ops.ct_projector import CTProjector

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
    from clgs.ops.ct_projector import CTProjector

    np.save(tmp_path / "ball.npy", ball_volume())
    common = ["--spacing", "2", "--views", 5, "--arc", 360, "--mode", "parallel", "--detector", 40, "--no-noise"]
    run("simulate", tmp_path / "ball.npy", *common, "--simulation", "same", "--out", tmp_path / "s")
    scan = Scan.load(tmp_path / "s")
    assert scan.geometry.mode == "parallel"
    same = CTProjector(scan.geometry).forward(scan.truth)
    assert np.array_equal(scan.projections, same)  # R2-Gaussian's protocol: the projector itself
    assert scan.meta["acquisition"]["noise"] is False
    # the default projects a grid twice as fine: the same object, not the same numbers
    run("simulate", tmp_path / "ball.npy", *common, "--out", tmp_path / "f")
    fine = Scan.load(tmp_path / "f")
    assert np.array_equal(fine.truth, scan.truth)
    rel = np.abs(fine.projections - same).max() / same.max()
    assert 1e-4 < rel < 0.1, rel
    assert fine.meta["acquisition"]["simulation"]["projected_grid"] == [48, 48, 48]


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
    assert sp == (2.0, 2.0, 2.0) and org == pytest.approx((-100.0, -50.0, 30.0))  # where the input lay
    assert f"{report['metrics']['psnr3d']:.4f}" in res.output
    res = run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec", "--filter", "hann")
    # the slice panel, and the bone surface at the level the scan's true surface was made at
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["report.json", "slices.png", "surface.json",
                                                                   "surface.stl", "volume.nii.gz", "volume.npy"]
    rep = json.loads((tmp_path / "rec" / "report.json").read_text())
    assert rep["method"] == "fdk" and rep["options"] == {"filter": "hann"} and rep["seconds"] > 0
    assert rep["slices"]["path"] == str(tmp_path / "rec" / "slices.png") and rep["slices"]["path"] in res.output
    assert rep["surface"]["surface_level"] == 0.005 and rep["surface"]["surface_level_source"] == "scan"
    assert f"{rep['surface']['distance_mean_mm']:.3f}" in res.output
    # existing outputs need --force
    res = run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec", ok=False)
    assert res.exit_code != 0 and "already exists" in res.output and "--force" in res.output
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec", "--force")


def test_a_folder_run_gets_slices_and_a_bone_surface_only_at_a_named_level(scan_dir, tmp_path):
    """R2-Gaussian mode knows no anatomy: no bone surface unless a level is named (--surface-level,
    or the scan's own); then report.json names it, with the distance of the file written."""
    trimesh = pytest.importorskip("trimesh")
    pytest.importorskip("rtree")
    sc = Scan.load(scan_dir / "scan")
    sc.meta.pop("truth_surface_level")
    sc.save(tmp_path / "plain")
    res = run("reconstruct", tmp_path / "plain", "-m", "sart", "--iterations", 2, "--out", tmp_path / "a")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["report.json", "slices.png", "volume.nii.gz",
                                                                 "volume.npy"]
    assert "bone surface: none written (no bone level" in res.output and "--surface-level" in res.output
    assert f"slices: {tmp_path / 'a' / 'slices.png'}" in res.output
    res = run("reconstruct", tmp_path / "plain", "-m", "r2gs", "--iterations", 30, "--gaussians", 400,
              "--no-progress", "--surface-level", 0.012, "--out", tmp_path / "b")
    rep = json.loads((tmp_path / "b" / "report.json").read_text())["surface"]
    assert rep["path"] == str(tmp_path / "b" / "surface.stl") and rep["surface_level_source"] == "user"
    assert rep["surface_level"] == 0.012 and "source: user" in res.output
    a, b = trimesh.load(tmp_path / "b" / "surface.stl"), trimesh.load(scan_dir / "scan" / "truth_surface.stl")
    d = [trimesh.proximity.closest_point(y, trimesh.sample.sample_surface(x, 20000, seed=k)[0])[1]
         for k, (x, y) in enumerate(((a, b), (b, a)))]
    assert float(np.concatenate(d).mean()) == pytest.approx(rep["distance_mean_mm"], rel=0.03, abs=0.02)
    res = run("reconstruct", tmp_path / "plain", "--surface-level", 0.01, "--out", tmp_path / "c.nii.gz", ok=False)
    assert res.exit_code == 2 and "give a folder as --out" in res.output


def test_a_scan_of_an_installed_anatomy_gets_its_bone_surface_sealed_as_the_anatomy_asks(scan_dir, tmp_path):
    """`clgs reconstruct` knows no anatomy, but a scan that names one (meta['anatomy'], as `clgs
    <anatomy> simulate` writes it) gets that anatomy's closing of holes in the bone's wall
    (docs/outputs.md); surface.json names it. Any other scan gets none."""
    pytest.importorskip("clgs_femur", reason="install with: pip install -e anatomies/femur")
    sc = Scan.load(scan_dir / "scan")
    sc.meta["anatomy"] = "femur"
    sc.save(tmp_path / "femur")
    run("reconstruct", tmp_path / "femur", "-m", "fdk", "--surface-level", 0.012, "--out", tmp_path / "a")
    record = json.loads((tmp_path / "a" / "surface.json").read_text())
    assert record["surface_closing_max_voxels"] == 3 and record["surface_closing_voxels"] in (0, 1, 2, 3)
    rep = json.loads((tmp_path / "a" / "report.json").read_text())["surface"]
    assert rep["surface_closing_max_voxels"] == 3
    sc.meta["anatomy"] = "no-such-bone"
    sc.save(tmp_path / "other")
    run("reconstruct", tmp_path / "other", "-m", "fdk", "--surface-level", 0.012, "--out", tmp_path / "b")
    assert "surface_closing_max_voxels" not in json.loads((tmp_path / "b" / "surface.json").read_text())


def _drilled_tube(scan, out_dir=None):
    """A 'reconstruction' that is a known answer: a hollow tube along z (outer radius 10 voxels, a
    3-voxel wall at 0.03/mm, the canal at 0.005, closed by 2-voxel lids) with a 2-voxel hole
    through its wall halfway along."""
    nz, ny, nx = scan.geometry.nVoxel
    _, y, x = np.mgrid[:nz, :ny, :nx].astype(np.float32)
    r = np.hypot(y - (ny - 1) / 2, x - (nx - 1) / 2)
    vol = np.where(r <= 10, np.where(r > 7, 0.03, 0.005), 0.0).astype(np.float32)
    vol[2:4][r[2:4] <= 10], vol[-4:-2][r[-4:-2] <= 10] = 0.03, 0.03
    vol[:2], vol[-2:] = 0.0, 0.0
    vol[nz // 2 - 1:nz // 2 + 1, ny // 2 - 1:ny // 2 + 1, nx // 2:] = 0.0  # the canal opens to the outside
    return {"volume": vol}


def test_surface_closing_seals_the_bone_surface_of_a_scan_that_names_no_anatomy(scan_dir, tmp_path):
    """`clgs reconstruct --surface-closing N` on a scan of no anatomy: the known-answer tube with a
    hole in its wall is written as its outer wall alone (trimesh: the area of the tube without
    the hole's inner surface), surface.json and the report name the closing; without it the
    canal's wall is written too. Given without a bone level it is refused before the run."""
    trimesh = pytest.importorskip("trimesh")
    sc = Scan.load(scan_dir / "scan")
    sc.meta.pop("truth_surface_level", None)
    sc.meta.pop("anatomy", None)
    sc.save(tmp_path / "plain")
    _register("tube_t", _drilled_tube)
    run("reconstruct", tmp_path / "plain", "-m", "tube_t", "--surface-level", 0.02, "--out", tmp_path / "open")
    run("reconstruct", tmp_path / "plain", "-m", "tube_t", "--surface-level", 0.02, "--surface-closing", 2,
        "--out", tmp_path / "sealed")
    opened, sealed = (trimesh.load(tmp_path / k / "surface.stl") for k in ("open", "sealed"))
    assert "surface_closing_max_voxels" not in json.loads((tmp_path / "open" / "surface.json").read_text())
    record = json.loads((tmp_path / "sealed" / "surface.json").read_text())
    assert record["surface_closing_max_voxels"] == 2 and record["surface_closing_voxels"] in (1, 2)
    rep = json.loads((tmp_path / "sealed" / "report.json").read_text())["surface"]
    assert rep["surface_closing_max_voxels"] == 2 and rep["surface_closing_voxels"] == record["surface_closing_voxels"]
    # the sealed surface is one closed shell, the outer wall; the open one also holds the canal's wall
    assert sealed.is_watertight and len(sealed.split(only_watertight=False)) == 1
    assert opened.area > 1.3 * sealed.area, (opened.area, sealed.area)
    # refused before the run: no level to write a surface at, or a volume file for --out
    res = run("reconstruct", tmp_path / "plain", "-m", "tube_t", "--surface-closing", 2, "--out", tmp_path / "x",
              ok=False)
    assert res.exit_code == 2 and "--surface-level" in res.output and not (tmp_path / "x").exists()
    res = run("reconstruct", tmp_path / "plain", "-m", "tube_t", "--surface-closing", 2, "--out", tmp_path / "x.nii.gz",
              ok=False)
    assert res.exit_code == 2 and "give a folder" in res.output
    res = run("reconstruct", tmp_path / "plain", "-m", "tube_t", "--surface-level", 0.02, "--surface-closing", 9,
              "--out", tmp_path / "x", ok=False)
    assert res.exit_code == 2 and "0<=x<=8" in res.output.replace(" ", "")
    ran = []

    def own_surface(scan, out_dir=None, surface_level=None):  # writes its own surface, takes no closing
        ran.append(scan)
        return _drilled_tube(scan)

    _register("own_surface_t", own_surface)
    res = run("reconstruct", tmp_path / "plain", "-m", "own_surface_t", "--surface-closing", 2,
              "--out", tmp_path / "y", ok=False)
    assert res.exit_code == 2 and "takes no surface closing" in res.output and "--surface-closing" in res.output
    assert not ran and not (tmp_path / "y").exists()


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
              "--json", tmp_path / "same.json", "--no-figure")
    same = json.loads((tmp_path / "same.json").read_text())
    assert same["psnr3d"] is None and same["ssim3d"] == pytest.approx(1.0) and "PSNR inf" in res.output
    assert same["surface"]["hausdorff"] == pytest.approx(0.0, abs=1e-9)
    # a reconstruct output folder is accepted as VOLUME
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec")
    res = run("evaluate", tmp_path / "rec", "--truth", scan_dir / "scan")
    assert f"{figures['psnr3d']:.4f}" in res.output


def test_evaluate_draws_the_slices_of_the_volume_the_truth_and_the_error(scan_dir, tmp_path):
    from PIL import Image

    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "fdk.nii.gz")
    res = run("evaluate", tmp_path / "fdk.nii.gz", "--truth", scan_dir / "scan", "--json", tmp_path / "e.json")
    png = tmp_path / "fdk_vs_truth.png"  # next to the volume
    assert f"figure: {png}" in res.output and json.loads((tmp_path / "e.json").read_text())["figure"] == str(png)
    w, h = Image.open(png).size
    assert h > w  # three rows of three square slices: the volume, the truth, the error
    run("reconstruct", scan_dir / "scan", "--out", tmp_path / "rec")
    res = run("evaluate", tmp_path / "rec", "--truth", scan_dir / "scan", "--figure", tmp_path / "f.png")
    assert (tmp_path / "f.png").is_file() and not (tmp_path / "rec" / "evaluation.png").exists()
    res = run("evaluate", tmp_path / "rec", "--truth", scan_dir / "scan", "--figure", tmp_path / "f.png", ok=False)
    assert "already exists" in res.output and "--force" in res.output
    run("evaluate", tmp_path / "rec", "--truth", scan_dir / "scan")
    assert (tmp_path / "rec" / "evaluation.png").is_file()
    res = run("evaluate", tmp_path / "rec", "--truth", scan_dir / "scan", "--figure", tmp_path / "f.jpg", ok=False)
    assert res.exit_code == 2 and "PNG" in res.output and not (tmp_path / "f.jpg").exists()
    res = run("evaluate", tmp_path / "rec", "--truth", scan_dir / "scan", "--figure", tmp_path / "g.png",
              "--no-figure", ok=False)
    assert res.exit_code == 2 and "not both" in res.output


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
    code = ("import sys; from click.testing import CliRunner; from clgs.cli import evaluate, reconstruct, simulate; "
            "commands = (simulate.simulate, reconstruct.reconstruct, evaluate.evaluate); "
            "outs = [CliRunner().invoke(c, ['--help']) for c in commands]; "
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


# ------------------------------------------------------------------------------ robustness of the inputs
def _tree(folder):
    """{relative path: bytes} of every file under ``folder``."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _register(name, run_fn, options=(), atomic_dir=True):
    from clgs import methods

    methods.register(methods.Method(name, run_fn, options=list(options), atomic_dir=atomic_dir, help="test"),
                     replace=True)


def test_output_may_not_replace_or_overwrite_the_input_scan(scan_dir, tmp_path):
    import click

    from clgs.io.r2gaussian import to_r2gaussian_folder

    scan = tmp_path / "data" / "scan"
    Scan.load(scan_dir / "scan").save(scan)
    before = _tree(scan)
    for out, json_out in [(scan, None),                      # the scan folder itself (atomic folder replace)
                          (tmp_path / "data", None),         # a folder holding the scan
                          (tmp_path, None),
                          (scan / "truth.npy", None),        # a file of the scan
                          (scan / "projections.npy", None),
                          (tmp_path / "v.npy", scan / "scan.json")]:  # the report over the scan's description
        args = ["reconstruct", scan, "--out", out, "--force"] + (["--json", json_out] if json_out else [])
        res = run(*args, ok=False)
        assert res.exit_code == 1 and "input scan" in res.output and "Traceback" not in res.output, res.output
        assert _tree(scan) == before
    assert not (tmp_path / "v.npy").exists()  # refused before the run: nothing half-done
    res = run("reconstruct", scan / "scan.json", "--out", scan, "--force", ok=False)  # the scan named by its json
    assert res.exit_code == 1 and "input scan" in res.output and _tree(scan) == before
    # a method that writes into its folder (resumable) may not use the scan folder either
    _register("resumable_t", _constant, [click.Option(["--resume"], is_flag=True, default=None)], atomic_dir=False)
    res = run("reconstruct", scan, "-m", "resumable_t", "--resume", "--out", scan, ok=False)
    assert res.exit_code == 1 and "input scan folder" in res.output and _tree(scan) == before
    # nor may a new file go next to the scan's files (the scan folder is the scan's alone)
    for method in ("fdk", "sart"):
        res = run("reconstruct", scan, "--method", method, "--out", scan / "fdk.nii.gz", ok=False)
        assert res.exit_code == 1 and "inside" in res.output and "scan folder" in res.output, res.output
    assert _tree(scan) == before
    # an R2-Gaussian folder's files are protected too
    to_r2gaussian_folder(Scan.load(scan_dir / "scan"), tmp_path / "r2")
    r2_before = _tree(tmp_path / "r2")
    for out in (tmp_path / "r2" / "proj_train", tmp_path / "r2" / "vol_gt.npy"):
        res = run("reconstruct", tmp_path / "r2", "--out", out, "--force", ok=False)
        assert res.exit_code == 1 and "input scan" in res.output
    assert _tree(tmp_path / "r2") == r2_before
    # simulate: --out may not be (or hold) the input volume
    (tmp_path / "vols").mkdir()
    np.save(tmp_path / "vols" / "v.npy", ball_volume())
    res = run("simulate", tmp_path / "vols" / "v.npy", "--spacing", 2, "--views", 2, "--detector", 16,
              "--out", tmp_path / "vols", "--force", ok=False)
    assert res.exit_code == 1 and "input volume" in res.output and (tmp_path / "vols" / "v.npy").is_file()


def test_non_finite_and_out_of_range_method_options_are_refused_at_parse_time(scan_dir, tmp_path):

    out = tmp_path / "run"
    for method, option, value in [("r2gs", "--tv", "nan"), ("r2gs", "--tv", "inf"), ("r2gs", "--dssim", "inf"),
                                  ("r2gs", "--scale-floor", "inf"), ("sart", "--relaxation", "nan"),
                                  ("constant_t", "--value", "inf"), ("constant_t", "--value", "1e999")]:
        _register("constant_t", _constant, CONSTANT_OPTIONS)
        res = run("reconstruct", scan_dir / "scan", "-m", method, option, value, "--out", out, ok=False)
        assert res.exit_code == 2 and f"'{option}'" in res.output and "finite" in res.output, res.output
        assert not out.exists() and list(tmp_path.iterdir()) == []  # no stray log.csv, no folder
    res = run("reconstruct", scan_dir / "scan", "-m", "r2gs", "--tv", "nan", "--out", out, ok=False)
    assert "x>=0" in res.output  # the option's own range is named
    # the type for method options (usable by any method's click options)
    from clgs.cli.options import FiniteFloat

    ff = FiniteFloat(min=0)
    assert ff.convert("0.5", None, None) == 0.5
    for bad in ("nan", "inf", "-inf", "1e999", "-1", "x"):
        with pytest.raises(__import__("click").BadParameter):
            ff.convert(bad, None, None)
    assert FiniteFloat()._describe_range() == "" and FiniteFloat().name == "float"


def test_seeds_name_the_option_and_its_range(scan_dir, tmp_path):
    np.save(tmp_path / "v.npy", ball_volume())
    res = run("simulate", tmp_path / "v.npy", "--spacing", 2, "--views", 2, "--detector", 16, "--seed", -1,
              "--out", tmp_path / "s", ok=False)
    assert res.exit_code == 2 and "'--seed'" in res.output and "0 to 2**64 - 1" in res.output
    assert not (tmp_path / "s").exists()
    for seed in (-1, 2 ** 64):
        res = run("reconstruct", scan_dir / "scan", "-m", "r2gs", "--seed", seed, "--out", tmp_path / "r", ok=False)
        assert res.exit_code == 2 and "'--seed'" in res.output and "0 to 2**64 - 1" in res.output, res.output
        assert not (tmp_path / "r").exists()
    from clgs.ct.noise import add_noise

    with pytest.raises(ValueError, match="seed"):
        add_noise(np.ones((1, 2, 2)), seed=-1)


@pytest.mark.skipif(not __import__("os").path.isdir("/proc/self"), reason="needs Linux /proc")
def test_unwritable_outputs_fail_before_the_run(scan_dir, tmp_path):
    for args in (["--out", "/proc/x.npy"], ["--out", "/proc/dir"],
                 ["--out", tmp_path / "v.npy", "--json", "/proc/j.json"]):
        res = run("reconstruct", scan_dir / "scan", *args, ok=False)
        assert res.exit_code == 1 and "cannot write" in res.output and "/proc" in res.output, res.output
        assert "fdk:" not in res.output  # nothing ran
    assert not (tmp_path / "v.npy").exists()  # the volume is not written when the report cannot be
    (tmp_path / "afile").write_text("x")
    for args in (["--out", tmp_path / "afile" / "v.npy"], ["--out", tmp_path / "afile" / "sub" / "rec"],
                 ["--out", tmp_path / "w.npy", "--json", tmp_path / "afile" / "r.json"]):
        res = run("reconstruct", scan_dir / "scan", *args, ok=False)
        assert res.exit_code == 1 and "is a file, not a folder" in res.output, res.output
    res = run("reconstruct", scan_dir / "scan", "--out", tmp_path / "same.json", "--json", tmp_path / "same.json",
              ok=False)
    assert res.exit_code == 2 and "same file" in res.output
    np.save(tmp_path / "v.npy", ball_volume())
    res = run("simulate", tmp_path / "v.npy", "--spacing", 2, "--out", "/proc/s", ok=False)
    assert res.exit_code == 1 and "cannot write" in res.output
    res = run("evaluate", tmp_path / "v.npy", "--spacing", 2, "--truth", scan_dir / "scan", "--json", "/proc/e.json",
              ok=False)
    assert res.exit_code == 1 and "cannot write" in res.output
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no probe left


def _out_of_memory(scan, out_dir=None):
    raise MemoryError()


def test_out_of_memory_names_the_volume_size(scan_dir, tmp_path):
    _register("oom_t", _out_of_memory)
    res = run("reconstruct", scan_dir / "scan", "-m", "oom_t", "--out", tmp_path / "r", ok=False)
    assert res.exit_code == 1 and "not enough memory" in res.output and "24x24x24 voxels" in res.output, res.output
    assert not (tmp_path / "r").exists()


def _fails_early(scan, out_dir=None, resume=False, interrupt=False, write=False):
    if write:
        (out_dir / "log.csv").write_text("iteration\n")
    if interrupt:
        raise KeyboardInterrupt
    raise ValueError("no checkpoint to resume from")


def test_a_failed_run_leaves_no_empty_output_folder(scan_dir, tmp_path):
    import click

    _register("early_t", _fails_early, [click.Option(["--resume"], is_flag=True, default=None),
                                        click.Option(["--interrupt"], is_flag=True, default=None),
                                        click.Option(["--write"], is_flag=True, default=None)], atomic_dir=False)
    out = tmp_path / "a" / "b" / "run"
    for extra, code in ((["--resume"], 1), (["--interrupt"], 130)):  # an error, or Ctrl-C while starting
        res = run("reconstruct", scan_dir / "scan", "-m", "early_t", *extra, "--out", out, ok=False)
        assert res.exit_code == code, res.output
        assert not (tmp_path / "a").exists()  # the folders this command made are gone again
    # a folder that existed before stays, and so does one the run wrote into
    out.mkdir(parents=True)
    run("reconstruct", scan_dir / "scan", "-m", "early_t", "--resume", "--out", out, ok=False)
    assert out.is_dir()
    # a new run that failed with nothing to resume from leaves nothing, so that running it again is not refused
    res = run("reconstruct", scan_dir / "scan", "-m", "early_t", "--write", "--out", tmp_path / "w", ok=False)
    assert res.exit_code == 1 and not (tmp_path / "w").exists()
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "checkpoint.pt").write_bytes(b"a run's last checkpoint")
    res = run("reconstruct", scan_dir / "scan", "-m", "early_t", "--write", "--resume", "--out", tmp_path / "w",
              ok=False)
    assert res.exit_code == 1 and (tmp_path / "w" / "checkpoint.pt").is_file()  # one to resume from is kept
    # atomic methods: a failure in a new nested folder leaves nothing either
    _register("oom_t", _out_of_memory)
    run("reconstruct", scan_dir / "scan", "-m", "oom_t", "--out", tmp_path / "x" / "y" / "rec", ok=False)
    run("reconstruct", scan_dir / "scan", "-m", "oom_t", "--out", tmp_path / "x" / "y" / "rec.npy",
        "--json", tmp_path / "j" / "r.json", ok=False)
    assert not (tmp_path / "x").exists() and not (tmp_path / "j").exists()


def test_simulate_refuses_impossible_noise(scan_dir, tmp_path):
    np.save(tmp_path / "v.npy", ball_volume())
    base = ["simulate", tmp_path / "v.npy", "--spacing", 2, "--views", 2, "--detector", 16, "--out", tmp_path / "s"]
    for option, value in [("--I0", "inf"), ("--I0", "nan"), ("--sigma", "inf"), ("--scatter", "nan"),
                          ("--I0", "0.001"), ("--I0", "1"), ("--arc", "nan"), ("--DSD", "inf"), ("--pixel", "inf"),
                          ("--surface-level", "nan")]:
        res = run(*base, option, value, ok=False)
        assert res.exit_code == 2 and f"'{option}'" in res.output, res.output
        assert not (tmp_path / "s").exists()
    res = run(*base, "--I0", "0.001", ok=False)
    assert "every projection is 0" in res.output
    # a low dose that saturates part of the detector is allowed, with a warning
    res = CliRunner().invoke(main, [str(a) for a in base] + ["--I0", "5"])
    assert res.exit_code == 0 and "warning:" in res.stderr and "raise --I0" in res.stderr
    acq = Scan.load(tmp_path / "s").meta["acquisition"]
    assert acq["saturated"] > 0
    res = CliRunner().invoke(main, [str(a) for a in base] + ["--force"])
    assert res.exit_code == 0 and "warning:" not in res.stderr
    assert Scan.load(tmp_path / "s").meta["acquisition"]["saturated"] == 0


def test_simulate_warns_of_a_volume_without_attenuation(tmp_path):
    """An all-zero volume casts no shadow: its scan is noise alone, and the user is told so."""
    np.save(tmp_path / "zero.npy", np.zeros((24, 24, 24), np.float32))
    base = ["simulate", tmp_path / "zero.npy", "--spacing", 2, "--views", 2, "--detector", 16]
    res = CliRunner().invoke(main, [str(a) for a in base] + ["--out", str(tmp_path / "s")])
    assert res.exit_code == 0 and "no ray crosses any attenuation" in res.stderr, res.output
    assert "nothing but noise" in res.stderr
    res = CliRunner().invoke(main, [str(a) for a in base] + ["--no-noise", "--out", str(tmp_path / "s2")])
    assert res.exit_code == 0 and "no ray crosses any attenuation" in res.stderr, res.output
    assert "nothing but noise" not in res.stderr
    # a volume that attenuates says nothing of it
    np.save(tmp_path / "ball.npy", ball_volume())
    res = CliRunner().invoke(main, ["simulate", str(tmp_path / "ball.npy"), "--spacing", "2", "--views", "2",
                                    "--detector", "16", "--out", str(tmp_path / "s3")])
    assert res.exit_code == 0 and "no ray crosses" not in res.stderr, res.output


def _recording(scan, out_dir=None, **kwargs):
    """Writes the keyword arguments it got; returns files as a list of paths (not a dict)."""
    (out_dir / "kwargs.json").write_text(json.dumps(kwargs))
    return {"volume": np.zeros(scan.geometry.nVoxel, np.float32), "files": [str(out_dir / "kwargs.json")]}


def test_resume_without_iterations_passes_none_and_files_may_be_a_list(scan_dir, tmp_path):
    import click

    _register("rec_t", _recording, [click.Option(["--iterations"], type=click.IntRange(min=1), default=None),
                                    click.Option(["--resume"], is_flag=True, default=None)], atomic_dir=False)
    out = tmp_path / "run"
    run("reconstruct", scan_dir / "scan", "-m", "rec_t", "--out", out)
    assert json.loads((out / "kwargs.json").read_text()) == {}  # a new run: the method's defaults
    report = json.loads((out / "report.json").read_text())
    assert report["files"] == {"kwargs.json": str(out / "kwargs.json")}
    run("reconstruct", scan_dir / "scan", "-m", "rec_t", "--resume", "--out", out)
    assert json.loads((out / "kwargs.json").read_text()) == {"resume": True, "iterations": None}
    assert json.loads((out / "report.json").read_text())["options"] == {"resume": True}
    run("reconstruct", scan_dir / "scan", "-m", "rec_t", "--resume", "--iterations", 40, "--out", out)
    assert json.loads((out / "kwargs.json").read_text()) == {"resume": True, "iterations": 40}


@pytest.mark.slow
def test_r2gs_resume_continues_to_the_planned_iterations(scan_dir, tmp_path):
    """--resume alone finishes an interrupted run at the iterations it was started with (not 30000);
    --resume --iterations N extends it. (A run stopped at 20 stands for an interrupted one.)"""
    out = tmp_path / "r2"

    def cli(*args):
        cmd = [sys.executable, "-m", "clgs.cli", "reconstruct", str(scan_dir / "scan"), "-m", "r2gs",
               "--out", str(out), "--no-progress", *map(str, args)]
        # a resume that wrongly trained to 30000 iterations fails on the timeout instead of hanging
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads((out / "report.json").read_text())["info"]["iterations"]

    assert cli("--iterations", 20, "--gaussians", 300, "--log-every", 0, "--checkpoint-every", 0) == 20
    assert cli("--resume") == 20
    assert cli("--resume", "--iterations", 40) == 40


@pytest.mark.parametrize("method, extra", [("sart", ["--iterations", 3]), ("r2gs", ["--iterations", 12])])
def test_a_constant_truth_costs_no_reconstruction(tmp_path, method, extra):
    """Metrics normalised by the truth's range are undefined on a constant truth: they are reported
    as undefined, and the reconstruction is written all the same."""
    np.save(tmp_path / "flat.npy", np.full((12, 12, 12), 0.02, np.float32))
    run("simulate", tmp_path / "flat.npy", "--spacing", 2, "--views", 4, "--detector", 24, "--no-noise",
        "--out", tmp_path / "scan")
    res = run("reconstruct", tmp_path / "scan", "--method", method, *extra, "--out", tmp_path / "rec")
    assert "metrics undefined" in res.output and "the truth is constant" in res.output
    assert (tmp_path / "rec" / "volume.nii.gz").is_file()


def test_volume_figures_report_undefined_metrics_and_still_raise_on_bad_input():
    from clgs import metrics

    flat = np.full((6, 6, 6), 0.5, np.float32)
    got = metrics.volume_figures(flat * 0.9, flat)
    assert got["psnr3d"] is None and got["ssim3d"] is None and "constant" in got["metrics_undefined"]
    ok = metrics.volume_figures(ball_volume(12, 4.0) * 0.9, ball_volume(12, 4.0))
    assert ok["psnr3d"] > 10 and 0 < ok["ssim3d"] <= 1 and "metrics_undefined" not in ok
    with pytest.raises(metrics.MetricError):
        metrics.volume_figures(flat[:5], flat)


@pytest.mark.slow
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_stopped_run_saves_and_exits_with_the_signal_status(scan_dir, tmp_path, sig, code):
    """SIGTERM (timeout, batch schedulers) and Ctrl-C: the run stops after its iteration, writes
    its outputs and checkpoint, says how to resume, and exits 128 + the signal, so that
    ``clgs reconstruct ... && clgs evaluate ...`` stops there."""
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    log = tmp_path / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "clgs.cli", "reconstruct", str(scan_dir / "scan"), "--method",
                                 "r2gs", "--iterations", "100000", "--out", str(out)],
                                stdout=subprocess.PIPE, stderr=err, text=True)
        deadline = time.time() + 120
        while time.time() < deadline and "train:" not in log.read_text():
            time.sleep(0.1)  # training has begun: its first progress line is out
        time.sleep(0.5)
        proc.send_signal(sig)
        stdout, _ = proc.communicate(timeout=120)
    stderr = log.read_text()
    assert proc.returncode == code, (stdout[-1000:], stderr[-2000:])
    assert "--resume" in stderr and (out / "checkpoint.pt").is_file() and (out / "volume.nii.gz").is_file()


def test_simulate_names_odd_volumes_and_sizes_before_any_work(tmp_path):
    np.save(tmp_path / "mask.npy", np.ones((8, 8, 8), bool))
    np.save(tmp_path / "cplx.npy", np.ones((8, 8, 8), complex))
    np.save(tmp_path / "ints.npy", np.full((8, 8, 8), 5, np.int16))
    np.save(tmp_path / "slab.npy", np.full((1, 32, 32), 0.02, np.float32))
    res = run("simulate", tmp_path / "mask.npy", "--spacing", 1, "--out", tmp_path / "a", ok=False)
    assert res.exit_code == 1 and "a mask" in res.output and not (tmp_path / "a").exists()
    res = run("simulate", tmp_path / "cplx.npy", "--spacing", 1, "--out", tmp_path / "b", ok=False)
    assert res.exit_code == 1 and "complex" in res.output
    res = run("simulate", tmp_path / "ints.npy", "--spacing", 1, "--views", 2, "--detector", 16,
              "--out", tmp_path / "c")
    assert "holds integers" in res.output and "--hu" in res.output
    res = run("simulate", tmp_path / "slab.npy", "--spacing", 1, "--views", 2, "--detector", 32,
              "--out", tmp_path / "d")
    assert "less than one detector row" in res.output
    for flags in (["--views", 10**9], ["--detector", 10**6]):
        res = run("simulate", tmp_path / "slab.npy", "--spacing", 1, *flags, "--out", tmp_path / "e", ok=False)
        assert res.exit_code == 1 and "GiB of memory" in res.output and not (tmp_path / "e").exists()


def test_line_integrals_that_overflow_are_a_message_not_a_traceback(tmp_path):
    np.save(tmp_path / "hot.npy", np.full((8, 8, 8), 3e38, np.float32))
    for noise in ([], ["--no-noise"]):
        res = run("simulate", tmp_path / "hot.npy", "--spacing", 1, "--views", 2, "--detector", 16, *noise,
                  "--out", tmp_path / "s", ok=False)
        assert res.exit_code == 1 and "overflow" in res.output and "units" in res.output
        assert not (tmp_path / "s").exists()


def test_reconstruct_takes_settings_as_the_anatomy_commands_do(scan_dir, tmp_path):
    """One way to pass method settings everywhere: --set KEY=VALUE (the method's own options after
    SCAN say the same); checked alike, and a setting given both ways is refused."""
    res = run("reconstruct", scan_dir / "scan", "--method", "sart", "--set", "iterations=2", "--set", "subsets=2",
              "--out", tmp_path / "a.nii.gz", "--json", tmp_path / "a.json")
    assert json.loads((tmp_path / "a.json").read_text())["options"] == {"iterations": 2, "subsets": 2}
    res = run("reconstruct", scan_dir / "scan", "--method", "sart", "--set", "iterations=2", "--iterations", 3,
              "--out", tmp_path / "b.nii.gz", ok=False)
    assert res.exit_code == 2 and "given both" in res.output
    res = run("reconstruct", scan_dir / "scan", "--method", "sart", "--set", "nope=1", "--out", tmp_path / "c.nii.gz",
              ok=False)
    assert res.exit_code == 2 and "unknown setting 'nope'" in res.output


def test_evaluate_refuses_volumes_on_different_world_grids(scan_dir, tmp_path):
    """Voxels are compared by index: a reconstruction and a truth that lie in different places
    (the same array moved, another voxel size) are refused with both grids; the input itself,
    where simulate and reconstruct keep it, is accepted."""
    run("reconstruct", scan_dir / "scan", "--method", "fdk", "--out", tmp_path / "fdk.nii.gz")
    run("evaluate", tmp_path / "fdk.nii.gz", "--truth", scan_dir / "ball.nii.gz")
    save_volume(tmp_path / "moved.nii.gz", ball_volume(), spacing=(2.0, 2.0, 2.0), origin=(-23.0, -23.0, -23.0))
    res = run("evaluate", tmp_path / "fdk.nii.gz", "--truth", tmp_path / "moved.nii.gz", ok=False)
    assert res.exit_code == 2 and "starts at" in res.output and "(-23.0, -23.0, -23.0)" in res.output
    save_volume(tmp_path / "fine.nii.gz", ball_volume(), spacing=(1.0, 1.0, 1.0))
    res = run("evaluate", tmp_path / "fdk.nii.gz", "--truth", tmp_path / "fine.nii.gz", ok=False)
    assert res.exit_code == 2 and "different grids" in res.output


def test_npy_axis_order_is_explicit(tmp_path):
    """R2-Gaussian's vol_gt.npy is [x, y, z]: --axes xyz reads it as such instead of transposing it
    silently; a file that carries its orientation is unaffected."""
    from clgs.io.scan import Scan

    xyz = np.zeros((12, 8, 4), np.float32)
    xyz[2:10, 2:6, 1:3] = 0.02
    np.save(tmp_path / "vol_gt.npy", xyz)
    run("simulate", tmp_path / "vol_gt.npy", "--spacing", 2, "--axes", "xyz", "--views", 2, "--detector", 16,
        "--no-noise", "--out", tmp_path / "s")
    truth = Scan.load(tmp_path / "s").truth
    assert truth.shape == (4, 8, 12) and np.array_equal(truth, xyz.transpose(2, 1, 0))
    np.save(tmp_path / "pred_xyz.npy", xyz)
    res = run("evaluate", tmp_path / "pred_xyz.npy", "--axes", "xyz", "--spacing", 2, "--truth", tmp_path / "s")
    assert "inf" in res.output or "PSNR" in res.output
    res = run("evaluate", tmp_path / "pred_xyz.npy", "--spacing", 2, "--truth", tmp_path / "s", ok=False)
    assert res.exit_code == 2 and "different shapes" in res.output


def test_the_shape_method_takes_its_anatomy_from_the_command_line(scan_dir, tmp_path, monkeypatch):
    """`clgs reconstruct SCAN --method shape --anatomy NAME` gives the run that anatomy (the option
    is not a setting of the method): an unknown name is the anatomy's error, and a known one reaches
    the run as its anatomy, not among its settings."""
    res = run("reconstruct", scan_dir / "scan", "--method", "shape", "--anatomy", "no_such_bone",
              "--out", tmp_path / "x", ok=False)
    assert res.exit_code != 0
    assert "no_such_bone" in res.output and "unknown setting" not in res.output
    import clgs.methods.run as R

    seen = {}

    def fake(method, scan, folder, settings=None, **kw):
        seen.update(settings=dict(settings or {}), **kw)
        return {"volume": np.zeros(scan.geometry.nVoxel, np.float32)}

    monkeypatch.setattr(R, "run_method", fake)
    run("reconstruct", scan_dir / "scan", "--method", "shape", "--anatomy", "femur", "--set", "iterations=3",
        "--out", tmp_path / "y")
    assert seen["anatomy"] == "femur" and "anatomy" not in seen["settings"]
    assert seen["settings"]["iterations"] == 3
