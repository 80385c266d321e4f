"""``clgs batch`` loses nothing: every row's output stays inside the batch folder, never in a scan,
never over a folder that is no run of the batch (checked before any run); SIGTERM and Ctrl-C stop
the batch like a run (the current run saves its checkpoint and is recorded as interrupted, exit
143 / 130) and the same command resumes it. A property test throws odd rows at it."""
import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from clgs.cli import main
from clgs.geometry import Geometry
from clgs.io.scan import Scan

ROOT = Path(__file__).resolve().parents[1]
N = 12


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A 5-view scan of a ball on a 12^3 grid, with its truth."""
    from clgs.ops.ct_projector import CTProjector

    geo = Geometry.default(n_views=5, n_voxel=N, n_detector=16, volume_mm=48.0)
    zz, yy, xx = np.mgrid[:N, :N, :N] - (N - 1) / 2
    truth = np.where(zz ** 2 + yy ** 2 + xx ** 2 < 16, 0.02, 0.0).astype(np.float32)
    proj = np.asarray(CTProjector(geo).forward(truth), np.float32)
    folder = tmp_path_factory.mktemp("batch_outputs") / "scans" / "s1"
    Scan(geo, proj, truth=truth).save(folder)
    return folder


def write_list(path, rows):
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=["scan", "method", "settings", "out"], lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") or "" for k in ("scan", "method", "settings", "out")})
    path.write_text(buf.getvalue())
    return path


def snapshot(root, skip) -> dict:
    """{path: (size, mtime, bytes of small files)} of everything under ``root`` but ``skip``."""
    out = {}
    for dirpath, _dirs, files in os.walk(root):
        if Path(dirpath) == skip or skip in Path(dirpath).parents:
            continue
        out[dirpath] = "dir"
        for f in files:
            p = Path(dirpath) / f
            st_ = p.stat()
            out[str(p)] = (st_.st_size, st_.st_mtime_ns, p.read_bytes() if st_.st_size < 4096 else None)
    return out


def batch(*args):
    return CliRunner().invoke(main, ["batch", *[str(a) for a in args], "--no-progress"])


def one_message(res):
    assert res.exit_code in (1, 2), res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output and res.output.count("Error:") == 1, res.output


# --------------------------------------------------------------------------------------- rows' outputs
def test_rows_may_write_only_inside_the_batch_folder_and_replace_nothing(scan, tmp_path):
    out = tmp_path / "b"
    out.mkdir()
    (out / "summary.json").write_text('{"counts": {}, "runs": []}')  # a batch folder from before
    (out / "theirs").mkdir()
    (out / "theirs" / "volume.npy").write_bytes(b"someone's volume")
    Scan.load(scan).save(out / "inner_scan")  # a scan kept inside the batch folder is an input all the same
    outside = tmp_path / "x"
    before = snapshot(tmp_path, out)
    for row_out, words in [("theirs", "no run of a batch"), (str(scan), "outside the batch"),
                           ("inner_scan", "scan folder"), ("inner_scan/run", "scan folder"),
                           ("../../x", "outside the batch"),
                           (str(outside), "outside the batch"), (".", "the batch folder"),
                           ("summary.json", "the batch folder or its summary"), ("y" * 300, "bytes long")]:
        lst = write_list(tmp_path / "l.csv", [{"scan": scan, "method": "fdk", "out": row_out}])
        res = batch(lst, "--out", out)
        one_message(res)
        assert words in res.output, (row_out, res.output)
        assert "run 1 (s1 fdk)" in res.output or row_out in ("theirs",), res.output
    lst = write_list(tmp_path / "l.csv", [{"scan": scan, "method": "fdk", "out": "a"},
                                          {"scan": scan, "method": "sart", "settings": "iterations=1", "out": "a/b"}])
    one_message(res := batch(lst, "--out", out))
    assert "one inside the other" in res.output
    assert (out / "theirs" / "volume.npy").read_bytes() == b"someone's volume"
    assert not outside.exists()
    after = snapshot(tmp_path, out)
    after.pop(str(tmp_path / "l.csv"), None)
    before.pop(str(tmp_path / "l.csv"), None)
    assert after == before
    # the batch folder must itself be new, empty or a batch folder; never a scan
    one_message(batch(write_list(tmp_path / "l.csv", [{"scan": scan, "method": "fdk"}]), "--out", scan.parent.parent))
    one_message(batch(write_list(tmp_path / "l.csv", [{"scan": scan, "method": "fdk"}]), "--out", scan / "runs"))
    assert not (scan / "runs").exists()


# --------------------------------------------------------------------------------------- signals
DRIVER = '''
import sys, time, signal
from pathlib import Path
import numpy as np
from clgs import methods

def slow(scan, out_dir=None, resume: bool = False, progress: bool = False):
    """Like a training run: takes SIGINT/SIGTERM itself, saves a checkpoint, returns interrupted."""
    out = Path(out_dir)
    if resume:
        assert (out / "checkpoint.pt").read_bytes() == b"iteration 7"
        (out / "resumed.txt").write_text("from iteration 7")
        return {"volume": np.full(scan.geometry.nVoxel, 0.5, np.float32)}
    got = []
    old = {s: signal.signal(s, lambda n, f: got.append(n)) for s in (signal.SIGINT, signal.SIGTERM)}
    (out / "started.txt").write_text("")
    try:
        while not got:
            time.sleep(0.02)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    (out / "checkpoint.pt").write_bytes(b"iteration 7")
    return {"volume": np.zeros(scan.geometry.nVoxel, np.float32), "info": {"interrupted": True, "stop_signal": got[0]}}

def hang(scan, out_dir=None):
    """Like FDK or SART: no signal handling of its own, nothing to save."""
    Path(out_dir, "started.txt").write_text("")
    while True:
        time.sleep(0.02)

methods.register(methods.Method("t-slow", slow, atomic_dir=False))
methods.register(methods.Method("t-hang", hang, atomic_dir=False))
from clgs.cli import main
main(sys.argv[1:], prog_name="clgs")
'''


def _start(tmp_path, lst, out):
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([sys.executable, str(driver), "batch", str(lst), "--out", str(out), "--no-progress"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path, proc):
    for _ in range(1200):
        if path.exists() or proc.poll() is not None:
            return
        time.sleep(0.05)


@pytest.mark.parametrize("sig,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_stops_the_batch_after_the_runs_checkpoint_and_a_rerun_resumes(scan, tmp_path, sig, code):
    out = tmp_path / "b"
    lst = write_list(tmp_path / "l.csv", [{"scan": scan, "method": "t-slow", "out": "a"},
                                          {"scan": scan, "method": "fdk", "out": "c"}])
    proc = _start(tmp_path, lst, out)
    _wait_for(out / "a" / "started.txt", proc)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == code, stderr
    assert "Traceback" not in stderr and "interrupted" in stdout + stderr
    summary = json.loads((out / "summary.json").read_text())
    assert {r["name"]: r["status"] for r in summary["runs"]} == {"a": "interrupted", "c": "pending"}
    assert summary["stop_signal"] == int(sig)
    assert json.loads((out / "a" / "run.json").read_text())["status"] == "interrupted"  # never "done"
    assert not (out / "c").exists()  # the next run never started
    # the same command again: the interrupted run continues from its checkpoint, the other runs
    proc = _start(tmp_path, lst, out)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    summary = json.loads((out / "summary.json").read_text())
    assert {r["name"]: r["status"] for r in summary["runs"]} == {"a": "done", "c": "done"}
    assert (out / "a" / "resumed.txt").read_text() == "from iteration 7"
    assert np.all(np.load(out / "a" / "volume.npy") == 0.5)


def test_a_run_that_cannot_save_is_cut_and_recorded_as_interrupted(scan, tmp_path):
    out = tmp_path / "b"
    lst = write_list(tmp_path / "l.csv", [{"scan": scan, "method": "t-hang", "out": "a"},
                                          {"scan": scan, "method": "fdk", "out": "c"}])
    proc = _start(tmp_path, lst, out)
    _wait_for(out / "a" / "started.txt", proc)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "Traceback" not in stderr, stderr
    summary = json.loads((out / "summary.json").read_text())
    assert {r["name"]: r["status"] for r in summary["runs"]} == {"a": "interrupted", "c": "pending"}
    assert not (out / "c").exists()
    assert not [p for p in out.iterdir() if p.name.endswith(".clgs-lock")]


# --------------------------------------------------------------------------------------- property
GOOD_OUTS = [None, "r", "sub/r", "ABS_INSIDE", "r/../r2"]
OUTS = st.one_of(st.sampled_from(GOOD_OUTS),
                 st.sampled_from(["../x", "../../x", "ABS_OUTSIDE", "SCAN", "SCAN_INNER", "theirs", ".", "summary.csv",
                                  "LONG", "/"]))
METHODS = st.one_of(st.sampled_from(["fdk", "sart"]), st.just("nope"))
# (sart takes iterations and subsets, fdk filter: the others are refused one way or another)
SETTINGS = st.one_of(st.sampled_from(["", "iterations=1"]),
                     st.sampled_from(["iterations=1e23", "iterations=0", "filter=hann", "bogus=1",
                                      "iterations=1;subsets=2", "relaxation=nan", "iterations=1.5"]))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.tuples(OUTS, METHODS, SETTINGS), min_size=1, max_size=2))
@example(rows=[(None, "fdk", ""), ("sub/r", "sart", "iterations=1")])
@example(rows=[("r", "fdk", ""), ("r/../r", "sart", "iterations=1")])
def test_any_list_rows_run_or_give_one_message_and_nothing_outside_changes(scan, tmp_path_factory, rows):
    root = tmp_path_factory.mktemp("prop")
    out = root / "d1" / "d2" / "batch"  # so that ../x and ../../x land under root, where changes are seen
    out.mkdir(parents=True)
    (out / "summary.json").write_text('{"counts": {}, "runs": []}')
    (out / "theirs").mkdir()
    (out / "theirs" / "notes.txt").write_text("not a run")
    where = {"ABS_OUTSIDE": str(root / "elsewhere"), "ABS_INSIDE": str(out / "abs"), "SCAN": str(scan),
             "SCAN_INNER": str(scan / "inner"), "LONG": "z" * 260}
    listed = [{"scan": scan, "method": m, "settings": s, "out": where.get(o, o)} for o, m, s in rows]
    lst = write_list(root / "l.csv", listed)
    before, scan_before = snapshot(root, out), snapshot(scan.parent, Path("/nonexistent"))
    res = batch(lst, "--out", out)
    if all(o in GOOD_OUTS for o, _, _ in rows) and all(m == "fdk" and s == "" or m == "sart" and s in (
            "", "iterations=1", "iterations=1;subsets=2") for _, m, s in rows) and len(
            {str((out / where.get(o, o or "x")).resolve()) for o, _, _ in rows}) == len(rows) and None not in [
            o for o, _, _ in rows[1:]]:
        assert res.exit_code == 0, res.output  # a good list runs
    if res.exit_code == 0:
        summary = json.loads((out / "summary.json").read_text())
        assert [r["status"] for r in summary["runs"]] == ["done"] * len(rows), res.output
        for r in summary["runs"]:
            assert Path(r["out"]).resolve().parent.is_relative_to(out.resolve())
            assert json.loads((Path(r["out"]) / "run.json").read_text())["status"] == "done"
    else:
        one_message(res)
    assert snapshot(root, out) == before
    assert snapshot(scan.parent, Path("/nonexistent")) == scan_before
    assert (out / "theirs" / "notes.txt").read_text() == "not a run"
