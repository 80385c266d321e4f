"""``clgs <anatomy> ...`` input handling: bad input is a click error (message, non-zero exit, no
traceback), --set and --views are checked before a run, --resume, and OUT/volume.npy is always
the volume just computed. Fast: a tiny scan, a bare anatomy and stand-in methods; the femur plugin
only where its subjects are the point (nothing there simulates or trains)."""
import os

import numpy as np
import pytest
from click.testing import CliRunner

from clgs import methods
from clgs.anatomy import Anatomy
from clgs.cli import main
from clgs.cli.anatomy_group import make_group
from clgs.geometry import Geometry
from clgs.io.scan import Scan
from clgs.io.volume import load_volume

N_VOX = 16
N_VIEWS = 6


def has_femur():
    try:
        from clgs.anatomy import plugins

        return "femur" in plugins.anatomy_names()
    except Exception:  # noqa: BLE001
        return False


needs_femur = pytest.mark.skipif(not has_femur(), reason="install with: pip install -e anatomies/femur")


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    """A 6-view scan of a ball on a 16^3 grid, with its truth."""
    from clgs.ops.ct_projector import CTProjector

    geo = Geometry.default(n_views=N_VIEWS, n_voxel=N_VOX, n_detector=24, volume_mm=64.0)
    zz, yy, xx = np.mgrid[:N_VOX, :N_VOX, :N_VOX] - (N_VOX - 1) / 2
    truth = np.where(zz ** 2 + yy ** 2 + xx ** 2 < 25, 0.02, 0.0).astype(np.float32)
    proj = np.asarray(CTProjector(geo).forward(truth), np.float32)
    folder = tmp_path_factory.mktemp("anatomy_cli") / "scan"
    Scan(geo, proj, truth=truth).save(folder)
    return folder


@pytest.fixture
def bare():
    """An anatomy with no loaders: the generic commands, default method r2gs."""
    return make_group(Anatomy(name="bare", summary="a bare anatomy"))


class Recorder:
    """A stand-in reconstruction method: records its call, returns a constant volume."""

    def __init__(self, value=1.0):
        self.value = value
        self.calls = []

    def __call__(self, scan, out_dir=None, iterations: int | None = None, resume: bool = False):
        self.calls.append({"n_views": scan.n_views, "out_dir": out_dir,
                           **({"iterations": iterations} if iterations is not None else {}),
                           **({"resume": resume} if resume else {})})
        return {"volume": np.full(tuple(scan.geometry.nVoxel), self.value, np.float32)}


@pytest.fixture
def stand_ins(monkeypatch):
    """Methods "t-zeros" (volume 0) and "t-ones" (volume 1), registered for one test."""
    made = {}
    for name, value in (("t-zeros", 0.0), ("t-ones", 1.0)):
        rec = Recorder(value)
        # the registry's own dict, restored afterwards
        monkeypatch.setitem(methods._REGISTRY, name, methods.Method(name, rec, help="test stand-in"))
        made[name] = rec
    return made


def invoke(group, *args):
    return CliRunner().invoke(group, [str(a) for a in args])


def assert_clean_error(res, *words, code=None):
    """A click error: non-zero exit through SystemExit (not an exception), the words in the message."""
    assert res.exit_code != 0, res.output
    if code is not None:
        assert res.exit_code == code, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    assert "Error" in res.output
    for w in words:
        assert w in res.output, res.output


# --------------------------------------------------------------------------------------- 1. volume.npy
def test_volume_npy_is_always_the_run_just_done(bare, stand_ins, tiny_scan, tmp_path):
    out = tmp_path / "rec"
    for i, (method, value) in enumerate((("t-zeros", 0.0), ("t-ones", 1.0), ("t-zeros", 0.0))):
        if i:  # a folder that holds a run is replaced only with --force
            assert_clean_error(invoke(bare, "reconstruct", tiny_scan, "--out", out, "--method", method),
                               "holds slices.png, volume.nii.gz, volume.npy", "--force")
        res = invoke(bare, "reconstruct", tiny_scan, "--out", out, "--method", method, *(["--force"] if i else []))
        assert res.exit_code == 0, res.output
        vol = np.load(out / "volume.npy")
        assert vol.shape == (N_VOX,) * 3 and np.all(vol == value), method
    # written atomically: no temporary left; no bone in a constant volume, so no surface.stl
    assert sorted(os.listdir(out)) == ["slices.png", "volume.nii.gz", "volume.npy"]


def test_fdk_then_sart_in_one_folder_keeps_the_sart_volume(bare, tiny_scan, tmp_path):
    out = tmp_path / "rec"
    assert invoke(bare, "reconstruct", tiny_scan, "--out", out, "--method", "fdk").exit_code == 0
    fdk = np.load(out / "volume.npy")
    res = invoke(bare, "reconstruct", tiny_scan, "--out", out, "--method", "sart", "--force",
                 "--set", "iterations=1", "--set", "progress=false")
    assert res.exit_code == 0, res.output
    sart = np.load(out / "volume.npy")
    assert not np.array_equal(sart, fdk) and sart.min() >= 0  # SART is non-negative, FDK is not
    assert fdk.min() < 0


@pytest.mark.slow
def test_resumed_r2gs_run_rewrites_volume_npy(bare, tiny_scan, tmp_path):
    """A resumed run's volume.npy is its own (it used to stay the first run's, unlike volume.nii.gz)."""
    out = tmp_path / "run"
    common = ["--method", "r2gs", "--set", "progress=false"]
    res = invoke(bare, "reconstruct", tiny_scan, "--out", out, *common, "--set", "iterations=2",
                 "--set", "n_gaussians=200", "--set", "log_every=0", "--set", "backend=torch")
    assert res.exit_code == 0, res.output
    first = np.load(out / "volume.npy")
    res = invoke(bare, "reconstruct", tiny_scan, "--out", out, "--resume", *common, "--set", "iterations=6")
    assert res.exit_code == 0, res.output
    npy, nii = np.load(out / "volume.npy"), load_volume(out / "volume.nii.gz").volume
    assert not np.array_equal(npy, first)
    np.testing.assert_allclose(npy, nii, rtol=1e-6, atol=1e-9)


# --------------------------------------------------------------------------------------- 2. errors
@pytest.mark.parametrize("setting, words", [
    ("foo=1", ["unknown setting 'foo'", "valid keys", "lambda_tv", "n_gaussians"]),
    ("iterations=abc", ["iterations=abc", "integer"]),
    ("iterations=2.5", ["iterations=2.5", "integer"]),
    ("backend=gpu", ["backend=gpu", "'cl', 'torch'"]),
    ("seed=-1", ["seed=-1"]),
    ("densify_interval=0", ["densify_interval must be >= 1, got 0"]),
    ("lambda_tv=NaN", ["lambda_tv=NaN", "finite"]),
    ("scale_bounds=[1]", ["scale_bounds"]),
    ("progress=maybe", ["progress=maybe", "true/false"]),
    ("anatomy=femur", ["unknown setting 'anatomy'"]),
    ("noequals", ["KEY=VALUE"]),
])
def test_bad_set_values_are_usage_errors_before_the_run(bare, stand_ins, tiny_scan, tmp_path, setting, words):
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "o", "--method", "r2gs", "--set", setting)
    assert_clean_error(res, "--set", *words, code=2)
    assert not (tmp_path / "o").exists()


@needs_femur
@pytest.mark.parametrize("setting, words", [
    ("lr_alpha=-1", ["lr_alpha must be >= 0, got -1"]),  # was "math domain error" after loading everything
    ("tau=0", ["tau=0", "0<x<=1"]),
    ("free_init=foo", ["free_init=foo"]),
    ("bogus=1", ["unknown setting 'bogus'", "lr_alpha", "tau", "level"]),
])
def test_bad_shape_settings_in_the_femur_group(tiny_scan, tmp_path, setting, words):
    res = CliRunner().invoke(main, ["femur", "reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"),
                                    "--set", setting])
    assert_clean_error(res, *words, code=2)


def test_good_settings_pass_and_are_converted():
    from clgs.cli.anatomy_group import _get_method
    from clgs.cli.settings import check_settings

    m, run = _get_method("r2gs")
    opts = {"iterations": 3, "n_gaussians": 200, "progress": False, "backend": "torch", "scale_bounds": None,
            "lambda_tv": 0, "resume": True}
    assert check_settings("r2gs", m, run, dict(opts)) == opts
    m, run = _get_method("fdk")
    assert check_settings("fdk", m, run, {"filter": "hann", "short_scan": "off"}) == {"filter": "hann",
                                                                                       "short_scan": "off"}
    with pytest.raises(Exception, match="valid keys: filter, short_scan"):
        check_settings("fdk", m, run, {"iterations": 3})


def test_corrupt_scan_is_a_clean_error(bare, tmp_path, tiny_scan):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "scan.json").write_text("not json")
    res = invoke(bare, "reconstruct", bad, "--out", tmp_path / "o", "--method", "fdk")
    assert_clean_error(res, "scan.json", code=1)
    # projections of the wrong size
    import shutil

    shutil.copytree(tiny_scan, tmp_path / "cut")
    np.save(tmp_path / "cut" / "projections.npy", np.zeros((2, 3, 4), np.float32))
    res = invoke(bare, "reconstruct", tmp_path / "cut", "--out", tmp_path / "o", "--method", "fdk")
    assert_clean_error(res, "projections", code=1)


def test_evaluate_garbage_or_missing_volume_is_a_clean_error(bare, tiny_scan, tmp_path):
    (tmp_path / "junk.npy").write_bytes(b"this is no array")
    assert_clean_error(invoke(bare, "evaluate", tmp_path / "junk.npy", tiny_scan), "junk.npy", code=1)
    np.save(tmp_path / "flat.npy", np.zeros((4, 4), np.float32))
    assert_clean_error(invoke(bare, "evaluate", tmp_path / "flat.npy", tiny_scan), "3-D", code=1)
    (tmp_path / "empty").mkdir()
    assert_clean_error(invoke(bare, "evaluate", tmp_path / "empty", tiny_scan), "volume.npy", code=1)


def test_resume_without_a_checkpoint_is_a_clean_error(bare, tiny_scan, tmp_path):
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "nothing", "--method", "r2gs", "--resume",
                 "--set", "progress=false")
    assert_clean_error(res, "checkpoint", code=1)


@needs_femur
def test_bad_model_file_is_a_clean_error(tiny_scan, tmp_path, monkeypatch):
    import clgs_femur

    monkeypatch.setenv("CLGS_CACHE_DIR", str(tmp_path / "cache"))
    path = clgs_femur.population_model().model_path  # what the femur's loaders read (follows the env)
    assert path.startswith(str(tmp_path))  # never the real cache
    os.makedirs(os.path.dirname(path))
    with open(path, "wb") as fh:
        fh.write(b"PK\x03\x04 not a model")
    res = CliRunner().invoke(main, ["femur", "reconstruct", str(tiny_scan), "--out", str(tmp_path / "o"),
                                    "--set", "iterations=2", "--set", "progress=false"])
    assert_clean_error(res, "model", code=1)


def test_programming_errors_keep_their_traceback(bare, tiny_scan, tmp_path, monkeypatch):
    def broken(scan, out_dir=None):
        return {}["volume"]  # a bug, not bad input

    monkeypatch.setitem(methods._REGISTRY, "t-broken", methods.Method("t-broken", broken))
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "o", "--method", "t-broken")
    assert isinstance(res.exception, KeyError)


@needs_femur
def test_simulate_unknown_subject_or_bad_mesh(tmp_path):
    res = CliRunner().invoke(main, ["femur", "simulate", "--subject", "99", "--out", str(tmp_path / "s")])
    assert_clean_error(res, "--subject", "'99'", "held out: 20, 21", code=2)
    (tmp_path / "bad.stl").write_text("solid nothing\nendsolid nothing\n")
    res = CliRunner().invoke(main, ["femur", "simulate", "--mesh", str(tmp_path / "bad.stl"),
                                    "--out", str(tmp_path / "s")])
    assert_clean_error(res, "bad.stl", code=1)
    res = CliRunner().invoke(main, ["femur", "simulate", "--views", "0", "--out", str(tmp_path / "s")])
    assert_clean_error(res, "--views", code=2)
    for arc in ("0", "-90", "1e9", "nan"):  # every view at one angle, or no arc at all
        res = CliRunner().invoke(main, ["femur", "simulate", "--arc", arc, "--out", str(tmp_path / "s")])
        assert_clean_error(res, "--arc", "0<x<=360", code=2)
    assert not (tmp_path / "s").exists()


# --------------------------------------------------------------------------------------- 3. --views
@pytest.mark.parametrize("views", [N_VIEWS + 1, 50, 0, -3])
def test_views_outside_the_scan_are_refused(bare, stand_ins, tiny_scan, tmp_path, views):
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "o", "--method", "t-ones", "--views", views)
    # a count below 1 is refused as the option is read (--views is always a count); more than the scan has, once read
    assert_clean_error(res, "--views", f"has {N_VIEWS} views" if views >= 1 else "x>=1", code=2)
    assert stand_ins["t-ones"].calls == []


@pytest.mark.parametrize("views", [1, 3, N_VIEWS, None])
def test_views_within_the_scan_are_used(bare, stand_ins, tiny_scan, tmp_path, views):
    args = [] if views is None else ["--views", views]
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "o", "--method", "t-ones", *args)
    assert res.exit_code == 0, res.output
    assert stand_ins["t-ones"].calls[0]["n_views"] == (views or N_VIEWS)


# --------------------------------------------------------------------------------------- 4. --resume
def test_resume_flag_passes_resume_and_no_default_iterations(bare, stand_ins, tiny_scan, tmp_path):
    rec = stand_ins["t-ones"]
    run = ["reconstruct", tiny_scan, "--out", tmp_path / "o", "--method", "t-ones"]
    assert invoke(bare, *run, "--resume").exit_code == 0
    assert rec.calls[-1] == {"n_views": N_VIEWS, "out_dir": str(tmp_path / "o"), "resume": True}  # no iterations
    assert invoke(bare, *run, "--resume", "--set", "iterations=7").exit_code == 0
    assert rec.calls[-1]["iterations"] == 7 and rec.calls[-1]["resume"] is True
    assert invoke(bare, *run, "--set", "resume=true").exit_code == 0  # the same thing, spelled as a setting
    assert rec.calls[-1]["resume"] is True and "iterations" not in rec.calls[-1]
    assert invoke(bare, *run, "--force").exit_code == 0  # a new run where one was: --force
    assert "resume" not in rec.calls[-1] and "iterations" not in rec.calls[-1]
    assert_clean_error(invoke(bare, *run, "--resume", "--force"), "--resume", "--force", code=2)  # contradictory
    n = len(rec.calls)
    assert_clean_error(invoke(bare, *run, "--resume", "--set", "resume=false"), "--resume", code=2)
    assert len(rec.calls) == n


def test_resume_is_refused_for_methods_without_checkpoints(bare, tiny_scan, tmp_path):
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "o", "--method", "fdk", "--resume")
    assert_clean_error(res, "fdk", "cannot resume", code=2)


def test_resume_is_in_the_help(bare):
    res = invoke(bare, "reconstruct", "--help")
    assert res.exit_code == 0 and "--resume" in res.output


# --------------------------------------------------------------------------------------- 5. demo, experiment
@needs_femur
@pytest.mark.parametrize("args, words", [
    (["--iterations", "0"], ["--iterations"]),
    (["--iterations", "-5"], ["--iterations"]),
    (["--views", "0"], ["--views"]),
    (["--subject", "99"], ["--subject", "'99'", "held out"]),
    (["--set", "lr_alpha=-1"], ["lr_alpha must be >= 0"]),
    (["--method", "r2gs", "--set", "foo=1"], ["unknown setting 'foo'"]),
])
def test_demo_bad_input(tmp_path, args, words):
    res = CliRunner().invoke(main, ["femur", "demo", "--out", str(tmp_path / "d"), *args])
    assert_clean_error(res, *words, code=2)
    assert not (tmp_path / "d").exists()  # refused before simulating anything


@needs_femur
@pytest.mark.parametrize("subjects, words", [
    ("99", ["'99'", "held-out", "20, 21, 22, 23, 24, 25"]),
    ("20,05", ["'05'", "held-out"]),  # a model subject: never evaluated on
    ("20,,21", ["''"]),
])
def test_experiment_subjects_must_be_held_out(tmp_path, subjects, words):
    res = CliRunner().invoke(main, ["femur", "experiment", "--subjects", subjects, "--out", str(tmp_path / "e")])
    assert_clean_error(res, "--subjects", *words, code=2)
    assert not (tmp_path / "e").exists()


def test_reconstruct_never_replaces_a_run_or_writes_into_its_scan(bare, tiny_scan, tmp_path):
    out = tmp_path / "rec"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"an earlier run")
    res = invoke(bare, "reconstruct", tiny_scan, "--out", out, "--method", "fdk")
    assert_clean_error(res, "holds a run already", "--resume", "--force")
    assert (out / "checkpoint.pt").read_bytes() == b"an earlier run"
    res = invoke(bare, "reconstruct", tiny_scan, "--out", out, "--method", "fdk", "--force")
    assert res.exit_code == 0, res.output
    assert (out / "volume.npy").is_file() and not (out / "checkpoint.pt").exists()
    for inside in (tiny_scan, tiny_scan / "runs"):
        res = invoke(bare, "reconstruct", tiny_scan, "--out", inside, "--method", "fdk")
        assert_clean_error(res, "scan")
    assert not (tiny_scan / "volume.npy").exists() and not (tiny_scan / "runs").exists()


def test_the_python_api_refuses_the_same(tiny_scan, tmp_path):
    from clgs import reconstruct_r2gs
    from clgs.fit.config import RunFolderError

    for inside in (tiny_scan, tiny_scan / "runs" / "r2gs"):
        with pytest.raises(RunFolderError, match="scan folder"):
            reconstruct_r2gs(Scan.load(tiny_scan), out_dir=inside, iterations=2, progress=False)
    held = tmp_path / "held"
    held.mkdir()
    (held / "checkpoint.pt").write_bytes(b"x")
    with pytest.raises(RunFolderError, match="holds a run already"):
        reconstruct_r2gs(Scan.load(tiny_scan), out_dir=held, iterations=2, progress=False)


def test_a_run_whose_loss_turns_nan_ends_in_a_message(bare, tiny_scan, tmp_path, monkeypatch):
    def diverging(scan, out_dir=None, **kw):
        raise FloatingPointError("the loss became nan at iteration 3 (view 1); lower the learning rates")

    monkeypatch.setitem(methods._REGISTRY, "t-nan", methods.Method("t-nan", diverging, help="test stand-in"))
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "r", "--method", "t-nan")
    assert_clean_error(res, "the loss became nan", code=1)
    assert "Traceback" not in res.output


@needs_femur
@pytest.mark.parametrize("command", ["simulate", "demo"])
def test_anatomy_sizes_are_checked_before_any_work(tmp_path, command):
    res = CliRunner().invoke(main, ["femur", command, "--views", "1000000000", "--out", str(tmp_path / "o")])
    assert_clean_error(res, "GiB of memory", "fewer --views", code=1)
    assert not (tmp_path / "o").exists()


def test_every_method_writes_a_nifti_a_viewer_places(bare, tiny_scan, tmp_path, stand_ins):
    import nibabel as nib

    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "r", "--method", "fdk")
    assert res.exit_code == 0, res.output
    img = nib.load(str(tmp_path / "r" / "volume.nii.gz"))
    scan = Scan.load(tiny_scan)
    assert img.shape == tuple(scan.geometry.nVoxel[::-1])
    assert np.allclose(np.diag(img.affine)[:3], scan.geometry.dVoxel[::-1])
    assert np.array_equal(np.asarray(img.dataobj).transpose(2, 1, 0), np.load(tmp_path / "r" / "volume.npy"))


@needs_femur
def test_demo_out_follows_the_output_rule(tmp_path):
    """`clgs femur demo --out D` claims D/scan and D/recon before any work: a second demo there is
    refused without --force (nothing touched), --force replaces the first one's clgs files, and a
    user's own folder D/scan is never replaced."""
    args = ["femur", "demo", "--method", "fdk", "--views", "2", "--out", str(tmp_path / "d")]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    first = (tmp_path / "d" / "recon" / "volume.npy").read_bytes()
    res = CliRunner().invoke(main, args)
    assert_clean_error(res, "already exists", "--force")
    assert (tmp_path / "d" / "recon" / "volume.npy").read_bytes() == first
    res = CliRunner().invoke(main, [*args, "--force"])
    assert res.exit_code == 0, res.output
    mine = tmp_path / "mine"
    (mine / "scan").mkdir(parents=True)
    (mine / "scan" / "notes.txt").write_text("my own notes")
    res = CliRunner().invoke(main, ["femur", "demo", "--method", "fdk", "--views", "2", "--out", str(mine), "--force"])
    assert_clean_error(res, "notes.txt")
    assert (mine / "scan" / "notes.txt").read_text() == "my own notes"


# --------------------------------------------------------------------------------------- the closing
def _open_tube(scan, out_dir=None):
    """A known answer: a hollow tube along z across the grid (a 2-voxel wall, lids at both ends)
    with a 2-voxel hole through its wall halfway along: the canal reaches the outside there."""
    n = tuple(scan.geometry.nVoxel)
    _, y, x = np.mgrid[:n[0], :n[1], :n[2]].astype(np.float32)
    r = np.hypot(y - (n[1] - 1) / 2, x - (n[2] - 1) / 2)
    vol = np.where(r <= 5, np.where(r > 2.9, 0.03, 0.005), 0.0).astype(np.float32)
    vol[2:4][r[2:4] <= 5], vol[-4:-2][r[-4:-2] <= 5] = 0.03, 0.03
    vol[:2], vol[-2:] = 0.0, 0.0
    c = n[0] // 2
    vol[c - 1:c + 1, n[1] // 2 - 1:n[1] // 2 + 1, n[2] // 2:] = 0.0
    return {"volume": vol}


def test_the_anatomy_groups_reconstruct_takes_a_closing(bare, tiny_scan, tmp_path, monkeypatch):
    """`clgs <anatomy> reconstruct --surface-closing N`: surface.json names the closing given (the
    bare anatomy asks for none) and the surface is the tube's outer wall alone, one shell (trimesh);
    without it the canal's wall is written too; a method that writes its own bone surface but
    takes no closing is refused before it runs."""
    trimesh = pytest.importorskip("trimesh")
    import json

    monkeypatch.setitem(methods._REGISTRY, "t-tube", methods.Method("t-tube", _open_tube, help="test stand-in"))
    for name, extra in (("open", ()), ("sealed", ("--surface-closing", 2))):
        res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / name, "--method", "t-tube",
                     "--surface-level", 0.02, *extra)
        assert res.exit_code == 0, res.output
    record = json.loads((tmp_path / "sealed" / "surface.json").read_text())
    assert record["surface_closing_max_voxels"] == 2 and record["surface_closing_voxels"] == 1
    assert "surface_closing_max_voxels" not in json.loads((tmp_path / "open" / "surface.json").read_text())
    opened, sealed = (trimesh.load(tmp_path / k / "surface.stl") for k in ("open", "sealed"))
    assert sealed.is_watertight and len(sealed.split(only_watertight=False)) == 1
    assert opened.area > 1.2 * sealed.area, (opened.area, sealed.area)
    ran = []

    def own_surface(scan, out_dir=None, surface_level=None):
        ran.append(scan)
        return {"volume": np.zeros(tuple(scan.geometry.nVoxel), np.float32)}

    monkeypatch.setitem(methods._REGISTRY, "t-own", methods.Method("t-own", own_surface, help="test stand-in"))
    res = invoke(bare, "reconstruct", tiny_scan, "--out", tmp_path / "x", "--method", "t-own", "--surface-closing", 1)
    assert_clean_error(res, "takes no surface closing", "--surface-closing", code=2)
    assert not ran and not (tmp_path / "x").exists()
