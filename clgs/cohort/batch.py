"""``clgs batch``: many scans x methods x settings, one output folder per run, one summary.

Runs come from a folder of scan folders (every method given, on every scan) or from a list, CSV or
JSON, one run per row with the columns

    scan       a scan folder (relative paths: from the list's folder)
    method     a method of :mod:`clgs.methods` (fdk, sart, r2gs, shape, ...)
    settings   optional: KEY=VALUE pairs as ``clgs reconstruct --set`` takes them, separated by ``;``
               (JSON: an object, or a list of KEY=VALUE strings)
    seed       optional: the run's seed (methods that take one)
    out        optional: the run's folder (relative: inside the batch's folder); default
               ``<scan>_<method>[_<settings hash>][_s<seed>]``

Each run is a task (:mod:`clgs.cohort.runner`): it loads its scan itself, reconstructs, writes the
volume (``volume.npy``, ``volume.nii.gz``) and the method's own files into its folder, then its
record ``run.json`` (atomically, last). A run whose folder holds a ``run.json`` made with the same
scan, method, settings and seed is finished: a batch run again skips it (resume). A run that fails
is listed with its error; the others go on. ``summary.csv`` and ``summary.json`` (in the batch's
folder) list every run, rewritten as each ends.
"""
from __future__ import annotations

import csv
import hashlib
import json
import os
import signal
from pathlib import Path

from clgs.errors import InputError
from clgs.methods.settings import parse_pairs

RECORD = "run.json"
SUMMARY_KEYS = ["name", "scan", "method", "settings", "seed", "status", "psnr3d", "ssim3d", "seconds", "error", "out"]
COLUMNS = {"scan", "method", "settings", "seed", "out"}


def split_settings(value) -> list:
    """A list's ``settings`` cell as KEY=VALUE strings: ``"a=1; b=2"``, ["a=1", ...] or {"a": 1}."""
    if value is None or value == "":
        return []
    if isinstance(value, dict):
        return [f"{k}={json.dumps(v)}" for k, v in value.items()]
    if isinstance(value, (list, tuple)):
        return [str(v).strip() for v in value if str(v).strip()]
    return [p.strip() for p in str(value).split(";") if p.strip()]


def read_list(path) -> list:
    """The runs of a CSV or JSON list: dicts with ``scan`` (absolute), ``method``, ``settings``
    (KEY=VALUE strings), ``seed`` (int or None) and ``out`` (or None)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"cannot read the batch list {path}: {exc.strerror or exc}") from None
    if path.suffix.lower() == ".json":
        try:
            rows = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"{path}: not JSON ({exc})") from None
        if isinstance(rows, dict) and isinstance(rows.get("runs"), list):
            rows = rows["runs"]
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise InputError(f"{path}: expected a list of objects (one per run) with keys {sorted(COLUMNS)}")
    elif path.suffix.lower() == ".csv":
        rows = [{k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items() if k}
                for r in csv.DictReader(text.splitlines())]
    else:
        raise InputError(f"{path}: a batch list is a .csv or .json file (or give a folder of scan folders)")
    runs = []
    for i, r in enumerate(rows, 1):
        unknown = sorted(set(r) - COLUMNS)
        if unknown:
            raise InputError(f"{path}, run {i}: unknown column(s) {unknown}; the columns are {sorted(COLUMNS)}")
        if not r.get("scan") or not r.get("method"):
            raise InputError(f"{path}, run {i}: scan and method are required")
        seed = r.get("seed")
        if seed in (None, ""):
            seed = None
        else:
            try:
                seed = int(seed)
            except (TypeError, ValueError):
                raise InputError(f"{path}, run {i}: seed {seed!r} is not a whole number") from None
            if seed < 0:
                raise InputError(f"{path}, run {i}: seed {seed} must be >= 0")
        scan = Path(str(r["scan"])).expanduser()
        runs.append({"scan": str(scan if scan.is_absolute() else (path.parent / scan).resolve()),
                     "method": str(r["method"]).strip(), "settings": split_settings(r.get("settings")),
                     "seed": seed, "out": (str(r["out"]) if r.get("out") not in (None, "") else None)})
    if not runs:
        raise InputError(f"{path} lists no runs")
    return runs


def scan_folders(folder) -> list:
    """The scan folders (holding ``scan.json``) directly inside ``folder``, sorted by name."""
    from clgs.io.scan import SCAN_JSON

    folder = Path(folder)
    found = sorted(p for p in folder.iterdir() if p.is_dir() and (p / SCAN_JSON).is_file())
    if not found:
        raise InputError(f"{folder} holds no scan folders (sub-folders with a {SCAN_JSON}); give a folder of "
                         "scan folders or a .csv/.json list")
    return [str(p.resolve()) for p in found]


def default_name(scan: str, method: str, settings: dict, seed) -> str:
    name = f"{Path(scan).name}_{method}"
    if settings:
        name += "_" + hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:8]
    if seed is not None:
        name += f"_s{seed}"
    return name


RESERVED = {"summary.csv", "summary.json"}  # the batch's own files


def _row(i: int, r: dict) -> str:
    return f"run {i} ({Path(str(r['scan'])).name} {r['method']})"


def plan(runs, out_dir) -> list:
    """Runs with their ``settings`` parsed, a ``name`` and an absolute ``out`` folder, each checked
    before any run: inside the batch folder (not the folder itself, nor its summary), never in a
    scan folder, names the file system takes, no two runs in one folder or one inside another."""
    from clgs.io.outputs import OutputError, check_place
    from clgs.methods.run import UnknownSettingError, check_method_settings

    out_dir = Path(os.path.abspath(out_dir)).resolve()
    planned, seen = [], {}
    for i, r in enumerate(runs, 1):
        settings = r["settings"] if isinstance(r["settings"], dict) else parse_pairs(r["settings"])
        try:  # an unknown key is refused before any run, as the command line and run_method refuse it
            check_method_settings(r["method"], settings)
        except UnknownSettingError as exc:
            raise InputError(f"{_row(i, r)}: {exc}") from None
        name = r.get("out") or default_name(r["scan"], r["method"], settings, r.get("seed"))
        given = Path(os.path.expanduser(str(name)))
        folder = Path(os.path.abspath(given if given.is_absolute() else out_dir / given))
        try:
            check_place(folder, within=out_dir, param=f"{_row(i, r)}: out", writable=False)
        except OutputError as exc:
            raise InputError(str(exc)) from None
        folder = folder.resolve()
        if folder == out_dir or folder.name in RESERVED and folder.parent == out_dir:
            raise InputError(f"{_row(i, r)}: out {name!r} is the batch folder or its summary; give the run a folder "
                             "of its own inside the batch folder")
        if str(folder) in seen:
            raise InputError(f"two runs would write to {folder} ({seen[str(folder)]} and {r['scan']} {r['method']}): "
                             "give them different out folders")
        for other in seen:
            if Path(other) in folder.parents or folder in Path(other).parents:
                raise InputError(f"{_row(i, r)}: its out folder {folder} and that of {seen[other]} ({other}) lie one "
                                 "inside the other; give the runs separate folders")
        seen[str(folder)] = f"{r['scan']} {r['method']}"
        planned.append({"name": os.path.relpath(folder, out_dir), "index": i,
                        "scan": str(r["scan"]), "method": r["method"], "settings": settings,
                        "seed": r.get("seed"), "out": str(folder)})
    return planned


def made_with(run: dict) -> dict:
    """What a run's record depends on: a kept record is reused only when these match."""
    return {"scan": run["scan"], "method": run["method"], "seed": run["seed"],
            "settings": json.loads(json.dumps(run["settings"], sort_keys=True, default=str))}


STATUS_RUNNING, STATUS_INTERRUPTED, STATUS_FAILED = "running", "interrupted", "failed"


def read_record(folder):
    """The run's ``run.json`` (None when there is none or it cannot be read). A record without a
    ``status`` is a finished run (records made before runs had one)."""
    try:
        record = json.loads((Path(folder) / RECORD).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _resume_settings(method: str, settings: dict) -> dict | None:
    """The settings that continue a method's run from its checkpoint, given to
    :func:`clgs.methods.run.run_method` with ``resume=True`` (None: the method cannot resume)."""
    from clgs.methods.run import method_accepts

    if not method_accepts(method, "resume"):
        return None
    return {k: settings[k] for k in ("iterations", "backend") if k in settings}


def batch_run(scan: str, method: str, settings: dict, seed, out: str) -> dict:
    """One run of a batch, wherever it runs: load the scan, reconstruct with ``method`` and
    ``settings`` (plus ``seed`` where the method takes one), score against the scan's truth when it
    has one, write the volume and then the record ``run.json``; returns the record.

    The run holds its folder's lock (:mod:`clgs.io.outputs`) and marks it ``running`` first. A run
    stopped by a signal returns a record with status ``interrupted`` (its checkpoint kept); run
    again, a run marked interrupted or running (a lost worker) with a checkpoint continues from it,
    any other attempt's files go first (only clgs's files) and it starts afresh."""
    import time

    import numpy as np

    from clgs import methods, metrics
    from clgs.fit.checkpoint import CheckpointError
    from clgs.fit.config import CHECKPOINT
    from clgs.io import atomic, outputs
    from clgs.io.reconstruction import save_reconstruction
    from clgs.io.scan import Scan
    from clgs.methods.run import check_method_settings, run_method

    check_method_settings(methods.get(method), settings)
    folder = Path(out)
    want = made_with({"scan": scan, "method": method, "seed": seed, "settings": settings})
    sc = Scan.load(scan)
    with outputs.lock(folder, param="out"):
        before = read_record(folder)
        resume = None
        if (before and before.get("status") in (STATUS_RUNNING, STATUS_INTERRUPTED)
                and {k: before.get(k) for k in want} == want and (folder / CHECKPOINT).is_file()):
            resume = _resume_settings(method, settings)
        if resume is None:
            outputs.clear(folder)  # an earlier attempt's files (a killed worker, a cut run): start afresh
        existed = folder.is_dir()
        folder.mkdir(parents=True, exist_ok=True)
        atomic.write_json(folder / RECORD, {**want, "status": STATUS_RUNNING})
        t0 = time.perf_counter()
        try:
            try:
                if resume is not None:
                    result = run_method(method, sc, str(folder), resume, resume=True, progress=False)
                else:
                    result = run_method(method, sc, str(folder), settings, seed=seed, progress=False)
            except CheckpointError:
                if resume is None:
                    raise
                outputs.clear(folder)  # a checkpoint that cannot be resumed: the run starts afresh
                atomic.write_json(folder / RECORD, {**want, "status": STATUS_RUNNING})
                result = run_method(method, sc, str(folder), settings, seed=seed, progress=False)
        except BaseException as exc:
            if (folder / CHECKPOINT).is_file():
                status = STATUS_INTERRUPTED if isinstance(exc, KeyboardInterrupt) else STATUS_FAILED
                atomic.write_json(folder / RECORD, {**want, "status": status})
            else:
                outputs.after_failure(folder, "folder", False, existed)
            raise
        seconds = time.perf_counter() - t0
        if not isinstance(result, dict) or "volume" not in result:
            raise InputError(f"method {method} returned no volume")
        info = result.get("info") or {}
        if info.get("interrupted"):  # stopped by a signal: its checkpoint is kept, the run is not finished
            record = {**want, "status": STATUS_INTERRUPTED, "stop_signal": info.get("stop_signal"),
                      "iteration": info.get("iterations"), "seconds": seconds}
            atomic.write_json(folder / RECORD, atomic.json_safe(record))
            return record
        vol = np.asarray(result["volume"], np.float32)
        if not np.all(np.isfinite(vol)):
            raise FloatingPointError(f"method {method} produced NaN or Inf voxels on {scan}")
        record = {**want, "status": "done", "seconds": seconds, "n_views": sc.n_views,
                  "process_peak_mib": process_peak_mib()}
        if sc.truth is not None:
            record.update(metrics.volume_figures(vol, sc.truth))
        record["volume_units"] = save_reconstruction(folder, vol, sc.geometry, folder=True)
        atomic.write_json(folder / RECORD, atomic.json_safe(record))
    return record


def process_peak_mib():
    """This process's peak resident memory so far (MiB; None where the platform does not say): in a
    worker, the largest of its runs so far plus the worker's own share."""
    try:
        import resource
        import sys
    except ImportError:  # pragma: no cover - not on every platform
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


def _summary_row(run: dict, status: str, record=None, error=None) -> dict:
    record = record or {}
    return {"name": run["name"], "scan": run["scan"], "method": run["method"],
            "settings": json.dumps(run["settings"], sort_keys=True) if run["settings"] else "",
            "seed": run["seed"], "status": status, "psnr3d": record.get("psnr3d"), "ssim3d": record.get("ssim3d"),
            "seconds": record.get("seconds"), "error": error, "out": run["out"]}


def write_summary(out_dir, rows, stop_signal=None) -> None:
    import io

    from clgs.io import atomic

    out_dir = Path(out_dir)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_KEYS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else r.get(k) for k in SUMMARY_KEYS})
    atomic.write_text(out_dir / "summary.csv", buf.getvalue())
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "kept", "failed", "interrupted", "pending")}
    atomic.write_json(out_dir / "summary.json", atomic.json_safe({"counts": counts, "runs": rows,
                                                                  "stop_signal": stop_signal}))


def _existing_run(run: dict) -> str | None:
    """What the run's folder holds already: None (nothing), ``kept`` (this run, finished) or
    ``again`` (this run, unfinished: interrupted, lost or failed). A folder that holds anything and
    is no run of a batch, or a run made with other settings, is refused: a batch replaces nothing."""
    from clgs.io.outputs import clgs_entries

    folder = Path(run["out"])
    where = f"run {run['index']} ({Path(run['scan']).name} {run['method']}): out {folder}"
    if os.path.lexists(folder) and not folder.is_dir():
        raise InputError(f"{where} is a file; a run writes a folder: give it another out")
    if not folder.is_dir():
        return None
    mine, other = clgs_entries(folder)
    if not mine and not other:
        return None
    record = read_record(folder)
    if record is None:
        shown = ", ".join((mine + other)[:4]) + (" ..." if len(mine + other) > 4 else "")
        raise InputError(f"{where} already holds {shown} and is no run of a batch (no readable {RECORD}); a batch "
                         "replaces nothing: give this run another out, or empty that folder")
    want = made_with(run)
    had = {k: record.get(k) for k in want}
    if had != want:
        diff = sorted(k for k in want if had[k] != want[k])
        raise InputError(f"{folder / RECORD} was made with other {', '.join(diff)} ({had}) than this batch asks "
                         f"for ({want}): give this run another out folder, or remove that one")
    return "kept" if record.get("status", "done") == "done" else "again"


def run_batch(runs, out_dir, workers: int | None = None, scheduler: str | None = None, progress: bool = True,
              echo=print) -> dict:
    """Run (or resume) a batch: ``runs`` as :func:`read_list` gives them (or dicts with ``scan``,
    ``method`` and optional ``settings`` (dict or KEY=VALUE strings), ``seed``, ``out``); returns
    the summary also written to ``out_dir/summary.json``.

    Every run's folder is checked before any run starts (:func:`plan`, :func:`_existing_run`), and
    the batch folder is locked while the batch runs (:mod:`clgs.io.outputs`). SIGINT (Ctrl-C) and
    SIGTERM stop the batch like a run: the run going on saves its checkpoint (Gaussian methods; FDK
    and SART are cut), it is recorded as ``interrupted``, no other run starts, and the summary's
    ``stop_signal`` names the signal; the same batch run again resumes it."""
    from clgs import methods
    from clgs.cohort.cluster import check_choice
    from clgs.cohort.runner import Stopped, Task, run_tasks, stop_signals
    from clgs.io import outputs

    check_choice(workers, scheduler)
    out_dir = Path(out_dir)
    runs = [dict({"settings": [], "seed": None, "out": None}, **r) for r in runs]
    for r in runs:
        try:
            methods.get(r["method"])
        except LookupError as exc:
            raise InputError(f"run on {r['scan']}: {exc}") from None
    try:
        outputs.check_output(out_dir, kind="batch")
    except outputs.OutputError as exc:
        raise InputError(str(exc)) from None
    planned = plan(runs, out_dir)
    with outputs.lock(out_dir):
        out_dir.mkdir(parents=True, exist_ok=True)
        rows, tasks = {}, []
        for run in planned:
            if _existing_run(run) == "kept":
                rows[run["name"]] = _summary_row(run, "kept", read_record(run["out"]))
                continue
            rows[run["name"]] = _summary_row(run, "pending")
            tasks.append(Task(run["name"], batch_run, kwargs={k: run[k] for k in ("scan", "method", "settings", "seed",
                                                                                  "out")}))
        kept = len(planned) - len(tasks)
        echo(f"batch: {len(planned)} runs, {kept} finished before (kept), {len(tasks)} to run -> {out_dir}")
        by_name = {r["name"]: r for r in planned}
        with stop_signals() as stop:

            def finished(outcome):
                run = by_name[outcome.key]
                if outcome.ok and (outcome.result or {}).get("status") == STATUS_INTERRUPTED:
                    rows[outcome.key] = _summary_row(run, STATUS_INTERRUPTED, outcome.result)
                    stop.request(outcome.result.get("stop_signal") or signal.SIGINT)
                elif outcome.ok:
                    rows[outcome.key] = _summary_row(run, "done", outcome.result)
                else:
                    rows[outcome.key] = _summary_row(run, "failed", error=outcome.error)
                    echo(f"  {outcome.key}: FAILED: {outcome.error}")
                write_summary(out_dir, [rows[r["name"]] for r in planned])

            write_summary(out_dir, [rows[r["name"]] for r in planned])
            try:
                run_tasks(tasks, workers=workers, scheduler=scheduler, on_outcome=finished, desc="batch runs",
                          progress=progress, echo=echo, stop=stop)
            except Stopped as exc:
                stop.request(exc.signum)
                for key in exc.running:  # cut where it stood (no checkpoint to keep, or none written yet)
                    rows[key] = _summary_row(by_name[key], STATUS_INTERRUPTED)
        if stop.signum is not None:
            for run in planned:  # runs a stopped cluster was running: their folders say so
                record = read_record(run["out"])
                if rows[run["name"]]["status"] == "pending" and record and record.get("status") in (
                        STATUS_RUNNING, STATUS_INTERRUPTED):
                    rows[run["name"]] = _summary_row(run, STATUS_INTERRUPTED)
        ordered = [rows[r["name"]] for r in planned]
        write_summary(out_dir, ordered, stop.signum)
    return json.loads((out_dir / "summary.json").read_text())
