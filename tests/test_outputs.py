"""Nothing lost anywhere: one rule for every output (clgs.io.outputs) from the command line, the
Python workflows and batch rows: an output that holds anything is refused without --force
(overwrite=True), --force removes only clgs's files, never inside a scan, names and writability
checked before any work, one run at a time per output (a lock naming the other run), a failed new
run leaves nothing behind. Tiny scans and stand-in methods; two processes where a lock is the point."""
import errno
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run
from click.testing import CliRunner

from clgs import methods
from clgs.anatomy import Anatomy
from clgs.cli.anatomy_group import make_group
from clgs.geometry import Geometry
from clgs.io import outputs
from clgs.io.scan import Scan

ROOT = Path(__file__).resolve().parents[1]
N = 16


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A 6-view scan of a ball on a 16^3 grid, with its truth."""
    from clgs.ops.ct_projector import CTProjector

    geo = Geometry.default(n_views=6, n_voxel=N, n_detector=24, volume_mm=64.0)
    zz, yy, xx = np.mgrid[:N, :N, :N] - (N - 1) / 2
    truth = np.where(zz ** 2 + yy ** 2 + xx ** 2 < 25, 0.02, 0.0).astype(np.float32)
    proj = np.asarray(CTProjector(geo).forward(truth), np.float32)
    folder = tmp_path_factory.mktemp("outputs") / "scan"
    Scan(geo, proj, truth=truth).save(folder)
    return folder


@pytest.fixture
def bare():
    return make_group(Anatomy(name="bare", summary="a bare anatomy"))


def invoke(group, *args):
    return CliRunner().invoke(group, [str(a) for a in args])


def clean_error(res, *words, code=1):
    assert res.exit_code == code, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    for w in words:
        assert w in res.output, res.output


def tree(folder) -> dict:
    """{relative path: bytes} of every file under ``folder``."""
    folder = Path(folder)
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def child_env():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


# --------------------------------------------------------------------------------------- 1. the rule
def test_a_finished_run_is_replaced_only_with_force_and_then_only_its_files(bare, scan, tmp_path):
    """FDK and SART run folders (no checkpoint) are protected like any other; --force removes the
    old run's files first, so an FDK run cannot report an earlier shape run's surface as its own."""
    out = tmp_path / "rec"
    assert invoke(bare, "reconstruct", scan, "--out", out, "--method", "fdk").exit_code == 0
    (out / "shape_surface.stl").write_text("solid an earlier shape-guided run\nendsolid\n")
    (out / "log.csv").write_text("iteration\n1\n")
    before = tree(out)
    for args in (["--method", "fdk"], ["--method", "sart", "--set", "iterations=1"]):
        res = invoke(bare, "reconstruct", scan, "--out", out, *args)
        clean_error(res, "already exists", "--force")
        assert tree(out) == before
    res = invoke(bare, "reconstruct", scan, "--out", out, "--method", "fdk", "--force")
    assert res.exit_code == 0, res.output
    left = sorted(os.listdir(out))  # the old run's other files are gone; the new run's own are there
    assert "shape_surface.stl" not in left and "log.csv" not in left
    assert {"volume.nii.gz", "volume.npy", "slices.png"} <= set(left)
    # the same from clgs reconstruct
    res = run("reconstruct", scan, "--method", "sart", "--iterations", 1, "--out", tmp_path / "r", ok=False)
    assert res.exit_code == 0
    res = run("reconstruct", scan, "--method", "fdk", "--out", tmp_path / "r", ok=False)
    clean_error(res, "already exists", "--force")
    (tmp_path / "r" / "log.png").write_bytes(b"an earlier run's figure")
    (tmp_path / "r" / "slices.png").write_bytes(b"an earlier run's figure")
    run("reconstruct", scan, "--method", "fdk", "--out", tmp_path / "r", "--force")
    assert sorted(os.listdir(tmp_path / "r")) == ["report.json", "slices.png", "volume.nii.gz", "volume.npy"]
    assert (tmp_path / "r" / "slices.png").read_bytes() != b"an earlier run's figure"
    assert json.loads((tmp_path / "r" / "report.json").read_text())["method"] == "fdk"


def test_force_never_deletes_what_no_clgs_run_wrote(bare, scan, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "volume.npy").write_bytes(b"x")
    (out / "notes.txt").write_text("my notes")
    for res in (invoke(bare, "reconstruct", scan, "--out", out, "--method", "fdk", "--force"),
                run("reconstruct", scan, "--out", out, "--force", ok=False),
                run("simulate", scan / "truth.npy", "--spacing", 4, "--out", out, "--force", ok=False)):
        clean_error(res, "notes.txt", "no clgs run writes")
    assert tree(out) == {"notes.txt": b"my notes", "volume.npy": b"x"}
    empty = tmp_path / "empty"
    empty.mkdir()  # an empty folder takes any output
    assert invoke(bare, "reconstruct", scan, "--out", empty, "--method", "fdk").exit_code == 0


def test_the_python_workflows_follow_the_same_rule(scan, tmp_path):
    from clgs import reconstruct_r2gs

    out = tmp_path / "fdk_run"
    out.mkdir()
    (out / "volume.nii.gz").write_bytes(b"a finished FDK run")
    (out / "report.json").write_text("{}")
    kw = dict(iterations=2, progress=False, n_gaussians=200, log_every=0, checkpoint_every=0, backend="torch")
    with pytest.raises(outputs.OutputError, match="overwrite=True"):
        reconstruct_r2gs(Scan.load(scan), out_dir=out, **kw)
    assert tree(out) == {"report.json": b"{}", "volume.nii.gz": b"a finished FDK run"}
    with pytest.raises(outputs.OutputError, match="contradict"):
        reconstruct_r2gs(Scan.load(scan), out_dir=out, resume=True, overwrite=True, **kw)
    res = reconstruct_r2gs(Scan.load(scan), out_dir=out, overwrite=True, **kw)
    assert "report.json" not in os.listdir(out) and res.volume.shape == (N, N, N)
    assert (out / "checkpoint.pt").is_file()


def test_resume_and_force_together_are_refused(bare, scan, tmp_path):
    res = invoke(bare, "reconstruct", scan, "--out", tmp_path / "o", "--method", "r2gs", "--resume", "--force")
    clean_error(res, "--resume", "--force", code=2)
    res = run("reconstruct", scan, "--method", "r2gs", "--resume", "--force", "--out", tmp_path / "o", ok=False)
    clean_error(res, "--resume", "--force", code=2)
    assert not (tmp_path / "o").exists()


def test_no_output_goes_inside_a_scan_folder(bare, scan, tmp_path):
    before = tree(scan)
    for method in ("fdk", "sart"):
        res = run("reconstruct", scan, "--method", method, "--out", scan / "fdk.nii.gz", ok=False)
        clean_error(res, "scan folder")
    res = invoke(bare, "reconstruct", scan, "--out", scan / "runs" / "a", "--method", "fdk")
    clean_error(res, "scan")
    assert tree(scan) == before


# --------------------------------------------------------------------------------------- 2. checked first
@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
def test_unwritable_and_overlong_outputs_fail_before_any_work(bare, scan, tmp_path, monkeypatch):
    calls = []

    def counting(sc, out_dir=None):
        calls.append(out_dir)
        return {"volume": np.zeros(sc.geometry.nVoxel, np.float32)}

    monkeypatch.setitem(methods._REGISTRY, "t-count", methods.Method("t-count", counting, atomic_dir=False))
    long_name = "x" * 300  # beyond any file system's names
    near = "y" * 245  # fits 255, but not with the temporary file's longer name
    for out, words in (("/proc/clgs-out", "cannot write"), (tmp_path / long_name, "bytes long"),
                       (tmp_path / near, "temporary file")):
        clean_error(invoke(bare, "reconstruct", scan, "--out", out, "--method", "t-count"), *words)
        clean_error(run("reconstruct", scan, "--method", "t-count", "--out", out, ok=False), *words)
        clean_error(run("reconstruct", scan, "--method", "fdk", "--out", f"{out}.nii.gz", ok=False), words[0])
        clean_error(run("simulate", scan / "truth.npy", "--spacing", 4, "--out", out, ok=False), words[0])
        lst = tmp_path / "list.csv"
        lst.write_text(f"scan,method,out\n{scan},fdk,{out}\n")
        clean_error(run("batch", lst, "--out", out, ok=False), words[0])
    assert calls == [] and not [p for p in tmp_path.iterdir() if p.name not in ("list.csv",)]


def test_a_failed_new_run_leaves_nothing_and_a_full_disk_says_resume(bare, scan, tmp_path, monkeypatch):
    from clgs.io import atomic

    def first_write_fails(sc, out_dir=None):
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "log.csv").write_text("iteration\n")
        with atomic.atomic_path(Path(out_dir) / "checkpoint.pt") as tmp:
            tmp.write_bytes(b"x")
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setitem(methods._REGISTRY, "t-full", methods.Method("t-full", first_write_fails, atomic_dir=False))
    res = run("reconstruct", scan, "--method", "t-full", "--out", tmp_path / "a", ok=False)
    clean_error(res, "disk is full", "run again")
    assert not (tmp_path / "a").exists()  # so "run again" is not refused
    clean_error(invoke(bare, "reconstruct", scan, "--out", tmp_path / "b", "--method", "t-full"), "run again")
    assert not (tmp_path / "b").exists()
    # a run whose periodic checkpoint is on disk: the message says --resume, and the folder stays for it
    out = tmp_path / "c"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"iteration 1000")
    with pytest.raises(atomic.DiskFullError, match="--resume"):
        _full(out / "checkpoint.pt")
    assert (out / "checkpoint.pt").read_bytes() == b"iteration 1000"


def _full(target):
    from clgs.io import atomic

    with atomic.atomic_path(target) as tmp:
        tmp.write_bytes(b"new")
        raise OSError(errno.ENOSPC, "No space left on device")


# --------------------------------------------------------------------------------------- 3. one run at a time
def _holder(path, ready):
    """A child process holding ``path``'s lock until killed."""
    code = ("import sys, time\nfrom clgs.io.outputs import lock\n"
            f"with lock({str(path)!r}):\n    open({str(ready)!r}, 'w').close()\n    time.sleep(300)\n")
    child = subprocess.Popen([sys.executable, "-c", code, "--out", str(path)], env=child_env())
    for _ in range(600):
        if ready.exists() or child.poll() is not None:
            break
        time.sleep(0.05)
    assert ready.exists(), "the child never took the lock"
    return child


def test_a_second_run_into_a_locked_folder_is_refused_and_a_dead_ones_lock_taken_over(bare, scan, tmp_path):
    out = tmp_path / "rec"
    child = _holder(out, tmp_path / "ready")
    try:
        res = invoke(bare, "reconstruct", scan, "--out", out, "--method", "fdk")
        clean_error(res, "being written by another clgs run", f"process {child.pid}", "--out")
        res = run("reconstruct", scan, "--method", "fdk", "--out", out, ok=False)
        clean_error(res, f"process {child.pid}")
        with pytest.raises(outputs.OutputBusy, match=str(child.pid)):
            from clgs import reconstruct_r2gs

            reconstruct_r2gs(Scan.load(scan), out_dir=out, iterations=2, progress=False)
    finally:
        child.kill()
        child.wait()
    assert outputs.lock_path(out).exists()  # a killed process leaves its lock file: taken over
    res = invoke(bare, "reconstruct", scan, "--out", out, "--method", "fdk")
    assert res.exit_code == 0, res.output
    assert not outputs.lock_path(out).exists()


def test_import_and_convert_outputs_follow_the_rule(scan, tmp_path):
    """`clgs import` claims its scan folder (refused without --force, a folder of someone else's
    files refused even with it, locked while written); `clgs convert` locks what it writes."""
    counts = np.full((6, 8, 24), 900.0, np.float32)
    counts[:, :, 8:16] = 500.0
    np.save(tmp_path / "raw.npy", counts)
    np.save(tmp_path / "flat.npy", np.full((8, 24), 1000.0, np.float32))
    args = ["import", tmp_path / "raw.npy", "--flats", tmp_path / "flat.npy", "--centre", "middle", "--arc", 180,
            "--mode", "parallel", "--out", tmp_path / "imp"]
    run(*args)
    clean_error(run(*args, ok=False), "already exists", "--force")
    run(*args, "--force")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    res = run(*args[:-1], mine, "--force", ok=False)
    clean_error(res, "notes.txt")
    assert (mine / "notes.txt").read_text() == "mine"
    out = tmp_path / "v.nii.gz"
    child = _holder(out, tmp_path / "ready")
    try:
        res = run("convert", scan / "truth.nii.gz", out, ok=False)
        clean_error(res, f"process {child.pid}")
    finally:
        child.kill()
        child.wait()
    run("convert", scan / "truth.nii.gz", out)
    assert out.is_file()


def test_an_experiment_folder_is_locked_while_it_runs(tmp_path):
    pytest.importorskip("clgs_femur")
    out = tmp_path / "exp"
    child = _holder(out, tmp_path / "ready")
    try:
        res = run("femur", "experiment", "--views", 2, "--subjects", "20", "--iterations", 5, "--out", out, ok=False)
        clean_error(res, f"process {child.pid}")
    finally:
        child.kill()
        child.wait()


def test_two_commands_at_once_into_one_folder(scan, tmp_path):
    """Two processes (SART, then FDK into the same --out while SART runs): the second is refused
    naming the first's process and command; the first's result is the one written."""
    out = tmp_path / "both"
    slow = subprocess.Popen([sys.executable, "-m", "clgs.cli", "reconstruct", str(scan), "--method", "sart",
                             "--iterations", "100000", "--out", str(out)], env=child_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(1200):
            if outputs.holder(out) or slow.poll() is not None:
                break
            time.sleep(0.05)
        assert outputs.holder(out)["pid"] == slow.pid
        fast = subprocess.run([sys.executable, "-m", "clgs.cli", "reconstruct", str(scan), "--method", "fdk",
                               "--out", str(out)], env=child_env(), capture_output=True, text=True, timeout=120)
        assert fast.returncode == 1 and "Traceback" not in fast.stderr, fast.stderr
        assert f"process {slow.pid}" in fast.stderr and "reconstruct" in fast.stderr and "sart" in fast.stderr
        assert "wrote" not in fast.stdout
    finally:
        slow.kill()
        slow.wait()


# --------------------------------------------------------------------------------------- 4. settings
def test_absurd_iteration_counts_are_refused_with_the_range(bare, scan, tmp_path):
    from clgs import reconstruct_r2gs

    for args in (["--method", "sart", "--set", "iterations=1e23"], ["--method", "r2gs", "--set", "iterations=1e23"],
                 ["--method", "sart", "--iterations", "100000000000"]):
        res = run("reconstruct", scan, *args, "--out", tmp_path / "o", ok=False)
        clean_error(res, "10,000,000" if "--set" in args else "10000000", code=2)
    clean_error(invoke(bare, "reconstruct", scan, "--out", tmp_path / "o", "--method", "r2gs", "--set",
                       "iterations=1e23"), "between 1 and 10,000,000", code=2)
    with pytest.raises(ValueError, match="between 1 and 10,000,000"):
        reconstruct_r2gs(Scan.load(scan), iterations=1e23, progress=False)
    assert not (tmp_path / "o").exists()


def test_worker_counts_beyond_the_machine_are_refused_and_dead_workers_explained(scan, tmp_path):
    from clgs.cohort import cluster
    from clgs.cohort.runner import _worker_error

    res = run("batch", scan.parent, "--out", tmp_path / "b", "--workers", 64 * cluster.cores(), ok=False)
    clean_error(res, "far beyond this machine", f"{cluster.cores()} cores", "GiB", "--workers")
    assert not (tmp_path / "b").exists()

    class KilledWorker(Exception):
        pass

    msg = _worker_error(KilledWorker("('clgs-x', <WorkerState ...>)"), 8)
    assert "died" in msg and "8 workers shared" in msg and "GiB each" in msg and "--workers" in msg


def test_a_second_model_build_waits_for_the_first_and_builds_nothing(tmp_path):
    """Two builds of one model file at once: the second waits for the first's lock, then finds its
    model up to date (it used to do the whole build again)."""
    from test_model_builder import FAST, MAX_CELLS, _counting, _population, _template

    from clgs.shape.builder import build_model

    out, ready = tmp_path / "m.npz", tmp_path / "ready"
    code = ("import sys\nfrom test_model_builder import FAST, MAX_CELLS, _population, _template\n"
            "from clgs.shape.builder import build_model\n"
            f"def hold(i, sid):\n    if i == 0:\n        open({str(ready)!r}, 'w').close()\n"
            "        __import__('time').sleep(3)  # mid-build: a second build without the lock would start now\n"
            f"build_model(_template(), _population(3, seed=3), {str(out)!r}, max_cells=MAX_CELLS, registration=FAST,"
            " progress=False, on_subject=hold)\n")
    env = child_env()
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "tests"), env["PYTHONPATH"]])
    child = subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE, text=True)
    for _ in range(2400):
        if ready.exists() or child.poll() is not None:
            break
        time.sleep(0.05)
    assert ready.exists(), child.stderr.read() if child.poll() is not None else "the child never started"
    log = []
    build_model(_template(), _counting(_population(3, seed=3), log), out, max_cells=MAX_CELLS, registration=FAST,
                progress=False)
    assert child.wait(timeout=300) == 0
    assert log == [] and out.is_file()  # nothing loaded, nothing registered: the first build's model
