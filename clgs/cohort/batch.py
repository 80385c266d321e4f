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
import inspect
import json
import os
from pathlib import Path

from clgs.errors import InputError

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


def parse_setting_pairs(pairs) -> dict:
    """KEY=VALUE strings -> {key: JSON value, else the string} (as ``clgs reconstruct --set``)."""
    out = {}
    for p in pairs:
        key, sep, text = str(p).partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key:
            raise InputError(f"a setting must read KEY=VALUE, got {p!r}")
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out


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


def plan(runs, out_dir) -> list:
    """Runs with their ``settings`` parsed, a ``name`` and an absolute ``out`` folder; two runs in
    one folder are refused."""
    out_dir = Path(out_dir).resolve()
    planned, seen = [], {}
    for r in runs:
        settings = r["settings"] if isinstance(r["settings"], dict) else parse_setting_pairs(r["settings"])
        name = r.get("out") or default_name(r["scan"], r["method"], settings, r.get("seed"))
        folder = Path(name) if Path(name).is_absolute() else out_dir / name
        folder = folder.resolve()
        if str(folder) in seen:
            raise InputError(f"two runs would write to {folder} ({seen[str(folder)]} and {r['scan']} {r['method']}): "
                             "give them different out folders")
        seen[str(folder)] = f"{r['scan']} {r['method']}"
        planned.append({"name": os.path.relpath(folder, out_dir) if out_dir in folder.parents else str(folder),
                        "scan": str(r["scan"]), "method": r["method"], "settings": settings,
                        "seed": r.get("seed"), "out": str(folder)})
    return planned


def _accepts(fn, method, key: str) -> bool:
    params = inspect.signature(fn).parameters
    if key in params:
        return True
    if any(p.kind == p.VAR_KEYWORD for p in params.values()) and method.config is not None:
        import dataclasses

        return key in {f.name for f in dataclasses.fields(method.config_class())}
    return False


def made_with(run: dict) -> dict:
    """What a run's record depends on: a kept record is reused only when these match."""
    return {"scan": run["scan"], "method": run["method"], "seed": run["seed"],
            "settings": json.loads(json.dumps(run["settings"], sort_keys=True, default=str))}


def batch_run(scan: str, method: str, settings: dict, seed, out: str) -> dict:
    """One run of a batch, wherever it runs: load the scan, reconstruct with ``method`` and
    ``settings`` (plus ``seed`` where the method takes one), score against the scan's truth when it
    has one, write the volume and then the record ``run.json``; returns the record."""
    import time

    import numpy as np

    from clgs import methods, metrics
    from clgs.io import atomic
    from clgs.io.scan import Scan
    from clgs.io.reconstruction import save_reconstruction

    m = methods.get(method)
    fn = m.callable()
    kwargs = dict(settings)
    if seed is not None and _accepts(fn, m, "seed"):
        kwargs["seed"] = int(seed)
    if _accepts(fn, m, "progress"):
        kwargs.setdefault("progress", False)
    from clgs.fit.config import CHECKPOINT

    folder = Path(out)
    sc = Scan.load(scan)
    folder.mkdir(parents=True, exist_ok=True)
    stale = folder / CHECKPOINT
    if stale.is_file() and not (folder / RECORD).is_file():
        # an earlier attempt's (a killed worker, Ctrl-C): this one starts afresh, as any run does
        stale.unlink()
    t0 = time.perf_counter()
    result = fn(sc, str(folder), **kwargs)
    seconds = time.perf_counter() - t0
    if not isinstance(result, dict) or "volume" not in result:
        raise InputError(f"method {method} returned no volume")
    vol = np.asarray(result["volume"], np.float32)
    if not np.all(np.isfinite(vol)):
        raise FloatingPointError(f"method {method} produced NaN or Inf voxels on {scan}")
    record = {**made_with({"scan": scan, "method": method, "seed": seed, "settings": settings}),
              "seconds": seconds, "n_views": sc.n_views, "process_peak_mib": process_peak_mib()}
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


def write_summary(out_dir, rows) -> None:
    import io

    from clgs.io import atomic

    out_dir = Path(out_dir)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_KEYS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else r.get(k) for k in SUMMARY_KEYS})
    atomic.write_text(out_dir / "summary.csv", buf.getvalue())
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "kept", "failed", "pending")}
    atomic.write_json(out_dir / "summary.json", atomic.json_safe({"counts": counts, "runs": rows}))


def run_batch(runs, out_dir, workers: int | None = None, scheduler: str | None = None, progress: bool = True,
              echo=print) -> dict:
    """Run (or resume) a batch: ``runs`` as :func:`read_list` gives them (or dicts with ``scan``,
    ``method`` and optional ``settings`` (dict or KEY=VALUE strings), ``seed``, ``out``); returns
    the summary also written to ``out_dir/summary.json``."""
    from clgs import methods
    from clgs.cohort.runner import Task, run_tasks

    out_dir = Path(out_dir)
    runs = [dict({"settings": [], "seed": None, "out": None}, **r) for r in runs]
    for r in runs:
        try:
            methods.get(r["method"])
        except LookupError as exc:
            raise InputError(f"run on {r['scan']}: {exc}") from None
    planned = plan(runs, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, tasks = {}, []
    for run in planned:
        rec_path = Path(run["out"]) / RECORD
        if rec_path.is_file():
            try:
                record = json.loads(rec_path.read_text())
            except (OSError, json.JSONDecodeError):
                record = None  # damaged: run again
            if record is not None:
                want = made_with(run)
                had = {k: record.get(k) for k in want}
                if had != want:
                    diff = sorted(k for k in want if had[k] != want[k])
                    raise InputError(f"{rec_path} was made with other {', '.join(diff)} ({had}) than this batch asks "
                                     f"for ({want}): give this run another out folder, or remove that one")
                rows[run["name"]] = _summary_row(run, "kept", record)
                continue
        rows[run["name"]] = _summary_row(run, "pending")
        tasks.append(Task(run["name"], batch_run, kwargs={k: run[k] for k in ("scan", "method", "settings", "seed",
                                                                              "out")}))
    kept = len(planned) - len(tasks)
    echo(f"batch: {len(planned)} runs, {kept} finished before (kept), {len(tasks)} to run -> {out_dir}")
    by_name = {r["name"]: r for r in planned}

    def finished(outcome):
        run = by_name[outcome.key]
        if outcome.ok:
            rows[outcome.key] = _summary_row(run, "done", outcome.result)
        else:
            rows[outcome.key] = _summary_row(run, "failed", error=outcome.error)
            echo(f"  {outcome.key}: FAILED: {outcome.error}")
        write_summary(out_dir, [rows[r["name"]] for r in planned])

    write_summary(out_dir, [rows[r["name"]] for r in planned])
    run_tasks(tasks, workers=workers, scheduler=scheduler, on_outcome=finished, desc="batch runs",
              progress=progress, echo=echo)
    ordered = [rows[r["name"]] for r in planned]
    write_summary(out_dir, ordered)
    return json.loads((out_dir / "summary.json").read_text())
