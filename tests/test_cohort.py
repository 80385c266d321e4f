"""Cohorts (clgs.cohort): runs as tasks here or on Dask, with the same results, resumed after an
interruption, surviving a killed worker, failed runs reported while the others finish.

On the toy plugin (a 40 x 40 x 56 grid, 3-4 views, 20 iterations); one local cluster of 2 worker
processes serves most tests (joined through its scheduler's address, as ``--scheduler`` does),
one test starts its own (``workers=2``)."""
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from cli_helpers import modules_loaded_by_help

ROOT = Path(__file__).resolve().parents[1]
TOY = ROOT / "examples" / "toy_plugin"
R2GS = {"log_every": 10, "checkpoint_every": 0}


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """The example plugin pip-installed into a folder on sys.path and PYTHONPATH (worker processes
    find it the same way), its model home in a temporary folder."""
    target = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index",
                        "--quiet", "--target", str(target), str(TOY)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    mp = pytest.MonkeyPatch()
    mp.syspath_prepend(str(target))
    mp.setenv("PYTHONPATH", os.pathsep.join([str(target), str(ROOT), os.environ.get("PYTHONPATH", "")]))
    mp.setenv("CLGS_TOY_HOME", str(tmp_path_factory.mktemp("toy-home")))
    from clgs.anatomy import plugins

    plugins.registry(reload=True)
    yield plugins.get_anatomy("toy")
    mp.undo()


@pytest.fixture(scope="module")
def cluster(toy):
    """A local Dask cluster of 2 worker processes (1 thread each, one clgs run at a time each)."""
    from distributed import Client, LocalCluster

    from clgs.cohort.cluster import RESOURCE, thread_env

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, resources={RESOURCE: 1},
                      env=thread_env(1), dashboard_address=None, silence_logs=40) as lc, Client(lc) as client:
        yield lc.scheduler_address, client


@pytest.fixture(scope="module")
def scans(toy, tmp_path_factory):
    """A folder with two toy scans (4 views) and a broken one."""
    from clgs.anatomy.simulation import simulate_subject

    folder = tmp_path_factory.mktemp("scans")
    for sid in ("08", "09"):
        simulate_subject(toy, toy.load_subject(sid), 4, math.pi, True, 1).save(folder / f"toy{sid}")
    (folder / "broken").mkdir()
    (folder / "broken" / "scan.json").write_text(json.dumps({"format": "clgs-scan", "version": 1}))
    return folder


def experiment(toy, out, **kw):
    from clgs.experiment import run_experiment

    lines = []
    summary = run_experiment(toy, out, views=(3,), subjects=["08"], iterations=20, ablation_views=None,
                             methods=("fdk", "r2gs"), seed=1, progress=False, settings={"r2gs": R2GS},
                             echo=lines.append, **kw)
    return summary, lines


def table_without_times(out: Path) -> list:
    """results.csv without its wall-time column (the one thing that depends on where a run ran)."""
    rows = [line.split(",") for line in (out / "results.csv").read_text().splitlines()]
    col = rows[0].index("seconds")
    return [r[:col] + r[col + 1:] for r in rows]


def record_without_times(path: Path) -> dict:
    row = json.loads(path.read_text())
    row.pop("seconds")
    row.pop("surface_file")
    row["history"] = [{k: v for k, v in h.items() if k != "seconds"} for h in row["history"]]
    return row


# --------------------------------------------------------------------------------------- experiment
@pytest.fixture(scope="module")
def serial_experiment(toy, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    summary, lines = experiment(toy, out)
    return out, summary, lines


def test_experiment_table_on_two_workers_equals_the_serial_one_bit_for_bit(toy, serial_experiment, tmp_path):
    serial, s_summary, _ = serial_experiment
    summary, lines = experiment(toy, tmp_path, workers=2)
    assert not summary["failed"] and not s_summary["failed"]
    table = table_without_times(tmp_path)
    assert len(table) == 3 and table == table_without_times(serial)  # header + fdk + r2gs, same digits
    for tag in ("08_3_fdk", "08_3_r2gs"):
        assert record_without_times(tmp_path / "runs" / f"{tag}.json") == record_without_times(
            serial / "runs" / f"{tag}.json")
    assert summary["per_method"]["3/r2gs"]["psnr3d"] == s_summary["per_method"]["3/r2gs"]["psnr3d"]
    assert any(line.startswith("Dask dashboard: http") for line in lines)


def test_an_interrupted_experiment_resumes_with_the_finished_runs_kept(toy, serial_experiment, tmp_path,
                                                                       monkeypatch):
    import clgs.experiment as exp

    real, calls = exp._run_one, []

    def interrupted_on_the_second_run(method, *args, **kwargs):
        calls.append(method)
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C in the middle of the experiment
        return real(method, *args, **kwargs)

    monkeypatch.setattr(exp, "_run_one", interrupted_on_the_second_run)
    with pytest.raises(KeyboardInterrupt):
        experiment(toy, tmp_path)
    assert sorted(p.name for p in (tmp_path / "runs").glob("*.json")) == ["08_3_fdk.json"]
    first = (tmp_path / "runs" / "08_3_fdk.json").read_bytes()
    summary, lines = experiment(toy, tmp_path)
    assert calls == ["fdk", "r2gs", "r2gs"]  # the finished run was not run again
    assert "08_3_fdk: done before, kept" in lines
    assert (tmp_path / "runs" / "08_3_fdk.json").read_bytes() == first
    assert table_without_times(tmp_path) == table_without_times(serial_experiment[0])


def test_a_signal_during_training_stops_the_experiment_and_the_run_is_not_recorded(toy, serial_experiment,
                                                                                 tmp_path, monkeypatch, capsys):
    """SIGTERM while R2-Gaussian mode trains: the trainer stops at its next iteration, the experiment
    records nothing for that run (an interrupted training is not a finished one), starts no other
    run and names the signal; the same call again runs it and gives the uninterrupted table."""
    from clgs.fit.trainer import Trainer

    real_step, sent = Trainer.step, []

    def step(self):
        if self.iteration == 5 and not sent:
            sent.append(self.iteration)
            os.kill(os.getpid(), signal.SIGTERM)
        return real_step(self)

    monkeypatch.setattr(Trainer, "step", step)
    summary, lines = experiment(toy, tmp_path)
    assert sent == [5] and summary["stop_signal"] == signal.SIGTERM
    assert sorted(p.name for p in (tmp_path / "runs").glob("*.json")) == ["08_3_fdk.json"]
    assert "  08_3_r2gs: stopped by SIGTERM; not recorded, it runs again on resume" in lines
    assert json.loads((tmp_path / "summary.json").read_text())["stop_signal"] == signal.SIGTERM
    # the run has no folder: nothing is said to be written or saved
    err = capsys.readouterr().err
    assert "interrupted at iteration 6: nothing written (the run has no output folder)" in err
    assert "checkpoint" not in err and "outputs so far written" not in err
    monkeypatch.setattr(Trainer, "step", real_step)
    summary, lines = experiment(toy, tmp_path)
    assert "stop_signal" not in summary and "08_3_fdk: done before, kept" in lines
    assert table_without_times(tmp_path) == table_without_times(serial_experiment[0])


def test_a_failed_run_is_listed_and_the_others_finish(toy, tmp_path, monkeypatch):
    import clgs.experiment as exp

    real = exp._run_one

    def r2gs_breaks(method, *args, **kwargs):
        if method == "r2gs":
            raise FloatingPointError("the loss turned NaN")
        return real(method, *args, **kwargs)

    monkeypatch.setattr(exp, "_run_one", r2gs_breaks)
    summary, lines = experiment(toy, tmp_path)
    assert summary["failed"] == {"08_3_r2gs": "FloatingPointError: the loss turned NaN"}
    assert (tmp_path / "runs" / "08_3_fdk.json").is_file() and not (tmp_path / "runs" / "08_3_r2gs.json").exists()
    assert "08_3_r2gs" in (tmp_path / "table.md").read_text().split("## Failed runs")[1]
    assert json.loads((tmp_path / "summary.json").read_text())["failed"] == summary["failed"]


# --------------------------------------------------------------------------------------- batch
def test_batch_list_reports_a_bad_scan_finishes_the_others_and_resumes(scans, cluster, tmp_path):
    from clgs.cohort.batch import read_list, run_batch

    address, _ = cluster
    (scans / "list.csv").write_text("scan,method,settings,seed,out\n"
                                    "toy08,r2gs,iterations=20;log_every=10,3,a\n"
                                    "broken,fdk,,,b\n"
                                    "toy09,fdk,,,c\n")
    runs = read_list(scans / "list.csv")
    assert runs[0]["settings"] == ["iterations=20", "log_every=10"] and runs[0]["seed"] == 3
    assert runs[1]["scan"] == str((scans / "broken").resolve()) and runs[1]["seed"] is None
    summary = run_batch(runs, tmp_path, scheduler=address, progress=False, echo=lambda *_: None)
    status = {r["name"]: r["status"] for r in summary["runs"]}
    assert status == {"a": "done", "b": "failed", "c": "done"} and summary["counts"]["failed"] == 1
    bad = next(r for r in summary["runs"] if r["name"] == "b")
    assert bad["error"].startswith("ScanError") and str(scans / "broken") in bad["error"]
    for name in ("a", "c"):
        rec = json.loads((tmp_path / name / "run.json").read_text())
        assert rec["psnr3d"] > 5 and (tmp_path / name / "volume.npy").is_file()
    assert not (tmp_path / "b").exists()
    csv_lines = (tmp_path / "summary.csv").read_text().splitlines()
    assert csv_lines[0].startswith("name,scan,method") and len(csv_lines) == 4 and ",failed," in csv_lines[2]
    # run again: finished runs kept (not rerun: their records stay byte for byte), the bad one tried again
    before = (tmp_path / "a" / "run.json").read_bytes()
    again = run_batch(runs, tmp_path, progress=False, echo=lambda *_: None)
    assert {r["name"]: r["status"] for r in again["runs"]} == {"a": "kept", "b": "failed", "c": "kept"}
    assert (tmp_path / "a" / "run.json").read_bytes() == before
    # a kept record made with other settings is refused, not mixed in
    runs[0]["settings"] = ["iterations=21"]
    from clgs.errors import InputError

    with pytest.raises(InputError, match="other settings"):
        run_batch(runs, tmp_path, progress=False, echo=lambda *_: None)


def test_a_worker_killed_mid_run_costs_that_run_only(scans, cluster, tmp_path):
    from clgs.cohort.batch import run_batch

    address, client = cluster
    runs = [{"scan": str(scans / f"toy{s}"), "method": "r2gs", "seed": 2, "out": f"r{s}",
             "settings": {"iterations": 150, "log_every": 0, "checkpoint_every": 10}} for s in ("08", "09")]
    killed = {}

    def kill_a_busy_worker():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not killed:
            busy = [w for w, keys in client.processing().items() if keys]
            if busy:
                time.sleep(1.0)  # well into the run
                pids = client.run(os.getpid, workers=busy[:1])
                (addr, pid), = pids.items()
                os.kill(pid, signal.SIGKILL)
                killed[addr] = pid
            time.sleep(0.1)

    killer = threading.Thread(target=kill_a_busy_worker, daemon=True)
    killer.start()
    summary = run_batch(runs, tmp_path, scheduler=address, progress=False, echo=lambda *_: None)
    killer.join(timeout=5)
    assert killed, "no worker was busy to be killed"
    assert [r["status"] for r in summary["runs"]] == ["done", "done"]
    assert all((tmp_path / f"r{s}" / "run.json").is_file() for s in ("08", "09"))
    pids = client.run(os.getpid)
    assert list(killed.values())[0] not in pids.values()  # the killed process is gone; the nanny started another
    # the killed attempt's checkpoint did not stop the new one (it started afresh, as a run does)
    assert all(json.loads((tmp_path / f"r{s}" / "run.json").read_text())["seed"] == 2 for s in ("08", "09"))


def test_batch_from_the_command_line_on_a_folder(scans, tmp_path):
    from click.testing import CliRunner

    from clgs.cli import main

    res = CliRunner().invoke(main, ["batch", str(scans), "--out", str(tmp_path / "b"), "-m", "fdk", "--seed", "4",
                                    "--no-progress"])
    assert res.exit_code == 1 and "1 run(s) failed" in res.output  # the broken scan
    assert "toy08_fdk_s4: done" in res.output and "toy09_fdk_s4: done" in res.output
    res = CliRunner().invoke(main, ["batch", str(scans), "--out", str(tmp_path / "b"), "-m", "fdk",
                                    "--set", "iterations=3"])
    assert res.exit_code == 2 and "no method of fdk takes it" in res.output
    res = CliRunner().invoke(main, ["batch", str(scans), "--out", str(tmp_path / "b"), "--workers", "2",
                                    "--scheduler", "tcp://127.0.0.1:1"])
    assert res.exit_code == 2 and "not both" in res.output


def test_lists_are_checked_before_any_run(tmp_path):
    from clgs.cohort.batch import plan, read_list
    from clgs.errors import InputError

    bad = {"x.csv": ("scan,method,colour\na,fdk,red\n", "unknown column"),
           "y.csv": ("scan,method,seed\na,fdk,-1\n", "must be >= 0"),
           "z.json": ('[{"scan": "a"}]', "scan and method are required"),
           "w.txt": ("", ".csv or .json")}
    for name, (text, words) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=words):
            read_list(tmp_path / name)
    (tmp_path / "v.json").write_text(json.dumps([{"scan": "s", "method": "sart", "settings": {"iterations": 3}},
                                                 {"scan": "s", "method": "sart", "settings": ["iterations=3"]}]))
    with pytest.raises(InputError, match="two runs would write to"):
        plan(read_list(tmp_path / "v.json"), tmp_path / "out")


# --------------------------------------------------------------------------------------- model build
def test_registrations_on_workers_make_the_same_model(toy, cluster, tmp_path):
    import numpy as np

    from clgs.cohort.registration import registration_runner
    from clgs.shape.builder import build_model

    address, _ = cluster
    template = toy.load_template()
    subjects = {sid: (lambda sid=sid: toy.load_subject(sid)) for sid in ("00", "01", "02")}
    settings = {"max_cells": 16, "registration": {"levels": [0], "iterations": [8]}, "progress": False}
    here = build_model(template, subjects, tmp_path / "here.npz", **settings)
    there = build_model(template, subjects, tmp_path / "there.npz", **settings,
                        run_registrations=registration_runner("toy", scheduler=address, progress=False, echo=None))
    with np.load(here) as a, np.load(there) as b:
        assert a.files == b.files
        for k in a.files:
            if k != "metadata":
                assert np.array_equal(a[k], b[k]), k


# --------------------------------------------------------------------------------------- start-up
def test_help_imports_no_dask():
    loaded = modules_loaded_by_help([["--help"], ["batch", "--help"], ["bench", "--help"]], ("dask", "distributed"))
    assert loaded == [], loaded


def test_experiment_and_build_model_take_the_cluster_options(toy, tmp_path):
    from click.testing import CliRunner

    from clgs.cli.anatomy_group import make_group

    group = make_group(toy)
    for cmd in (["experiment", "--out", str(tmp_path / "e")], ["build-model", "--out", str(tmp_path / "m.npz")]):
        res = CliRunner().invoke(group, [*cmd, "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"])
        assert res.exit_code == 2 and "not both" in res.output, res.output
        res = CliRunner().invoke(group, [*cmd, "--scheduler", "127.0.0.1:1"])
        assert res.exit_code == 2 and "tcp://HOST:PORT" in res.output, res.output
    assert not (tmp_path / "e").exists() and not (tmp_path / "m.npz").exists()


def test_bench_cohort_prints_runs_per_minute_for_one_and_two_workers(toy):
    from click.testing import CliRunner

    from clgs.cli import main

    res = CliRunner().invoke(main, ["bench", "cohort", "--anatomy", "toy", "--views", "3", "--no-per-task",
                                    "--runs", "2", "--runs-method", "fdk"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    rows = [line.split() for line in res.output.splitlines() if line.strip()[:1].isdigit()]
    assert [r[0] for r in rows] == ["1", "2"], res.output  # one row per worker count, same 2 runs
    assert all(float(r[2]) > 0 and r[-1].startswith("x") for r in rows)
    assert rows[0][-1] == "x1.00" and "machine during the run" in res.output


def test_a_run_started_again_after_a_lost_attempt_starts_afresh(scans, tmp_path):
    """A killed worker may leave the run's checkpoint behind without its record: the next attempt
    does not take it for a finished run, nor for one to refuse."""
    from clgs.cohort.batch import batch_run

    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "checkpoint.pt").write_bytes(b"half a run")
    rec = batch_run(str(scans / "toy08"), "r2gs", {"iterations": 5, "log_every": 0, "checkpoint_every": 0}, 1,
                    str(folder))
    assert rec["psnr3d"] > 5 and (folder / "run.json").is_file()
    assert not (folder / "checkpoint.pt").exists() or (folder / "checkpoint.pt").read_bytes() != b"half a run"


def test_a_cluster_without_dask_is_a_clear_error_before_any_work(monkeypatch):
    """Dask is the ``cluster`` extra: asking for workers without it says what to install."""
    import importlib.util

    from clgs.cohort import cluster
    from clgs.errors import InputError

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name in ("dask", "distributed")
                        else real(name, *a))
    assert cluster.distributed_wanted(0, None) is False  # no cluster asked for: nothing needed
    with pytest.raises(InputError, match=r"pip install 'clgs\[cluster\]'"):
        cluster.distributed_wanted(2, None)
