"""The one rule for every output clgs writes (a run folder, a volume file, a scan folder, a batch):

* an output that holds anything is refused unless the caller says to replace it (``--force`` on
  the command line, ``overwrite=True`` in Python); a run folder is resumed only when asked;
* replacing removes the old output's files first, and only files clgs writes (:data:`CLGS_FILES`,
  plus those the old run's report lists): a folder holding anything else is refused even with
  ``--force``, naming what it holds, so clgs never deletes what it did not make;
* an output never lies inside a scan folder (one holding ``scan.json`` or ``meta_data.json``);
  inside a batch it stays inside the batch folder (``within``);
* its names fit the file system, the temporary names of atomic writes included, and its folder
  accepts files: both checked before any work;
* while a run writes an output it holds an exclusive lock on it (``.<name>.clgs-lock`` beside
  it, an OS lock that dies with its process): a second run is refused with the first one's process
  id and command; the lock of a process that died is taken over;
* a new run that fails with nothing to resume from leaves nothing behind; one that can be resumed
  (its checkpoint) keeps its folder (and a full disk then says ``--resume``: :mod:`clgs.io.atomic`).

:func:`claim` applies all of it; every command and the Python workflows go through it. Only the
standard library.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path

from clgs.errors import ClgsError

__all__ = ["OutputError", "OutputBusy", "CLGS_FILES", "claim", "check_output", "check_place", "check_names", "lock",
           "holder", "held", "clear", "is_scan_folder", "clgs_entries", "after_failure"]


class OutputError(ClgsError, ValueError):
    """An output that would lose work, land inside an input, or cannot be written."""


class OutputBusy(OutputError):
    """Another process is writing the same output now."""


CHECKPOINT = "checkpoint.pt"
# every name a clgs command writes into a run, batch or scan folder: replacing a folder removes these only
RUN_FILES = {"volume.nii.gz", "volume.npy", "report.json", "run.json", CHECKPOINT, "config.json", "gaussians.npz",
             "log.csv", "log.png", "summary.txt", "alpha.json", "surface.stl", "shape_surface.stl",
             "shape_uncertainty.ply", "shape_uncertainty.vtk", "surface_distance.png", "surface.json", "slices.png",
             "evaluation.png"}
SCAN_FILES = {"scan.json", "projections.npy", "truth.npy", "truth.nii.gz", "truth_surface.stl"}
CLGS_FILES = frozenset(RUN_FILES | SCAN_FILES)
SCAN_MARKERS = ("scan.json", "meta_data.json")
LOCK_SUFFIX = ".clgs-lock"
# the longest prefix clgs.io.atomic adds to a name for its temporary sibling: ".<12 hex>.tmp."
TEMP_PREFIX = 18
# the longest name clgs writes inside a run folder, with its temporary prefix
INNER_NAME = TEMP_PREFIX + max(len(n) for n in CLGS_FILES)


def _is_own_leftover(name: str) -> bool:
    """A lock or an atomic write's temporary (``.<12 hex>.tmp.NAME``, ``.<12 hex>.old.NAME``)."""
    if name.endswith(LOCK_SUFFIX):
        return True
    parts = name.split(".", 3)
    return name.startswith(".") and len(parts) == 4 and len(parts[1]) == 12 and parts[2] in ("tmp", "old")


def _entries(folder: Path) -> list:
    try:
        return sorted(p for p in os.listdir(folder) if not _is_own_leftover(p))
    except OSError:
        return []


def _listed(folder: Path) -> set:
    """Names the old run's report (``report.json`` of ``clgs reconstruct``) lists as its files."""
    try:
        doc = json.loads((folder / "report.json").read_text(encoding="utf-8"))
        files = doc.get("files") or {}
        values = files.values() if isinstance(files, dict) else files
        return {Path(str(v)).name for v in values if Path(str(v)).parent.name == folder.name}
    except (OSError, ValueError, AttributeError, TypeError):
        return set()


def clgs_entries(folder) -> tuple:
    """(entries clgs writes, other entries) of ``folder``."""
    folder = Path(folder)
    known = CLGS_FILES | _listed(folder)
    names = _entries(folder)
    return [n for n in names if n in known and not (folder / n).is_symlink()], \
           [n for n in names if n not in known or (folder / n).is_symlink()]


def is_scan_folder(folder) -> bool:
    return any(os.path.isfile(os.path.join(folder, m)) for m in SCAN_MARKERS)


def _shown(names, n: int = 4) -> str:
    names = list(names)
    return ", ".join(names[:n]) + (f" and {len(names) - n} more" if len(names) > n else "")


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return 255


def _path_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_PATH_MAX"))
    except (OSError, ValueError, AttributeError):
        return 4096


def _nearest_existing(path: Path) -> Path:
    while not os.path.lexists(path) and path.parent != path:
        path = path.parent
    return path


def check_names(path, param: str = "--out", folder: bool = True) -> None:
    """Every name of ``path`` fits the file system with the temporary prefix atomic writes add
    (and, for a folder, with the longest name written inside it): checked before any work, not at
    the end of a computation."""
    target = Path(os.path.abspath(path))
    base = _nearest_existing(target)
    name_max, path_max = _name_max(base if base.is_dir() else base.parent), _path_max(base)
    for part in target.relative_to(base).parts if target != base else (target.name,):
        if len(part.encode()) + TEMP_PREFIX > name_max:
            raise OutputError(f"cannot write {param} {path}: the name {part[:40]}... is {len(part.encode())} bytes "
                              f"long; this file system takes {name_max}, and clgs needs {TEMP_PREFIX} more for the "
                              f"temporary file it writes first, so at most {name_max - TEMP_PREFIX}. Choose a shorter "
                              f"{param}")
    longest = len(str(target).encode()) + (1 + INNER_NAME if folder else TEMP_PREFIX)
    if longest >= path_max:
        raise OutputError(f"cannot write {param} {path}: its path is {len(str(target).encode())} bytes long and the "
                          f"files written there would reach {longest}, beyond this system's {path_max}. Choose a "
                          f"shorter {param}")


def _check_writable(path: Path, param: str) -> None:
    """The folder that takes ``path`` accepts new files (for an existing folder: the folder
    itself, where its run writes): tested by making and removing an empty folder there (permission
    bits say nothing to root, nor on read-only or virtual file systems such as /proc)."""
    where = Path(path) if Path(path).is_dir() else _nearest_existing(Path(os.path.abspath(path)).parent)
    if not where.is_dir():
        raise OutputError(f"cannot write {param} {path}: {where} is a file, not a folder; choose another {param}")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".clgs-write-test-", dir=where))
    except OSError as exc:
        raise OutputError(f"cannot write {param} {path}: files cannot be created in {where} "
                          f"({exc.strerror or exc}); choose another {param}") from None


def check_output(path, *, kind: str = "folder", overwrite: bool = False, resume: bool = False, within=None,
                 param: str = "--out", force_word: str = "--force") -> None:
    """Refuse, before any work, an output that breaks the rule above (see the module doc).

    ``kind``: ``folder`` (a run folder), ``scan`` (a scan folder being written), ``batch`` (a
    batch folder: resumed when it is one) or ``file``. ``within``: a folder the output must lie
    inside (a batch's). ``force_word``: how the caller's users say overwrite (``--force``,
    ``overwrite=True``)."""
    path = Path(path)
    if resume and overwrite:
        raise OutputError(f"resume and {force_word} contradict each other: resume continues the run in {path}, "
                          f"{force_word} replaces it; give one")
    check_place(path, kind=kind, within=within, param=param, writable=False)
    if os.path.lexists(path):
        _check_existing(path, kind, overwrite, resume, param, force_word)
    _check_writable(path, param)


def check_place(path, *, kind: str = "folder", within=None, param: str = "--out", writable: bool = True) -> None:
    """Where ``path`` lies, whatever it holds: names that fit, inside ``within``, never in a scan
    folder, and (``writable``) a folder that accepts files."""
    path = Path(path)
    check_names(path, param, folder=kind != "file")
    target = Path(os.path.abspath(path)).resolve()
    if within is not None:
        inside = Path(os.path.abspath(within)).resolve()
        if target != inside and inside not in target.parents:
            raise OutputError(f"{param} {path} lies outside the batch folder {within}; a batch writes only inside "
                              "its folder: give a relative name without '..'")
    for folder in (target, *target.parents):
        if folder == target and kind == "scan":
            continue
        if is_scan_folder(folder):
            where = "is" if folder == target else f"lies inside {folder}, which is"
            raise OutputError(f"{param} {path} {where} a scan folder: outputs never go into a scan (they could "
                              f"replace or mix with its files); choose another {param}")
    if writable:
        _check_writable(path, param)


def _check_existing(path: Path, kind: str, overwrite: bool, resume: bool, param: str, force_word: str) -> None:
    if kind == "file":
        if path.is_dir():
            raise OutputError(f"{param} {path} is a folder; a volume file cannot replace it: choose another {param}")
        if not overwrite:
            raise OutputError(f"{path} already exists; pass {force_word} to replace it (or choose another {param})")
        return
    if not path.is_dir():
        raise OutputError(f"{param} {path} exists and is a file, not a folder; remove it or choose another {param}")
    mine, other = clgs_entries(path)
    if not mine and not other:
        return  # an empty folder takes any output
    if kind == "batch":
        if (path / "summary.json").is_file() or (path / "summary.csv").is_file():
            return  # a batch folder: the batch resumes there
        if not overwrite:
            raise OutputError(f"{param} {path} holds {_shown(mine + other)} and is not a batch folder (no "
                              f"summary.json): choose an empty or new {param}")
        return
    if resume:
        return  # the method checks its checkpoint
    if not overwrite:
        if CHECKPOINT in mine:
            held = f"holds a run already ({CHECKPOINT}); resume it (--resume, resume=True), or pass {force_word} to "
        else:
            held = f"already exists and holds {_shown(mine + other)}; pass {force_word} to "
        held += "replace it"
        raise OutputError(f"{path} {held} (or choose another {param})")
    if other:
        raise OutputError(f"{param} {path} holds {_shown(other)}, which no clgs run writes; {force_word} replaces "
                          f"only a clgs output's own files, so it is refused here: move them, or choose another "
                          f"{param}")


def clear(path) -> list:
    """Remove the files clgs wrote in the folder (or the file) ``path``; returns the names removed."""
    path = Path(path)
    if not path.is_dir():
        if os.path.lexists(path):
            path.unlink()
            return [path.name]
        return []
    mine, _ = clgs_entries(path)
    for name in mine:
        p = path / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    return mine


# ------------------------------------------------------------------------------ locks
_HELD: dict = {}  # resolved output path -> lock file descriptor (this process's locks)


def _key(path) -> str:
    return str(Path(os.path.abspath(path)).resolve())


def lock_path(path) -> Path:
    """Where ``path``'s lock lies: beside it, or inside an existing folder whose parent takes no files."""
    path = Path(os.path.abspath(path))
    beside = path.with_name(f".{path.name}{LOCK_SUFFIX}")
    if path.is_dir() and not os.access(path.parent, os.W_OK | os.X_OK):
        return path / LOCK_SUFFIX
    return beside


def holder(path) -> dict | None:
    """What the lock file of ``path`` says of the process holding it (or that last held it)."""
    try:
        doc = json.loads(lock_path(path).read_text(encoding="utf-8"))
        return doc if isinstance(doc, dict) else None
    except (OSError, ValueError):
        return None


def _command() -> str:
    argv = [os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "python"] + sys.argv[1:]
    text = " ".join(argv)
    return text if len(text) <= 300 else text[:297] + "..."


def _busy(path, param: str) -> OutputBusy:
    who = holder(path) or {}
    since = who.get("started")
    when = f", since {time.strftime('%H:%M:%S', time.localtime(since))}" if isinstance(since, (int, float)) else ""
    host = f" on {who['host']}" if who.get("host") and who.get("host") != socket.gethostname() else ""
    return OutputBusy(f"{param} {path} is being written by another clgs run: process {who.get('pid', '?')}{host} "
                      f"({who.get('command', 'unknown command')}){when}. Wait for it to end, or choose another "
                      f"{param}")


def _pid_alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except (OSError, ValueError, TypeError):
        return False
    return True


def _acquire(path, param: str, wait: bool = False) -> int:
    """An exclusive OS lock on ``path``'s lock file (released when this process ends, however)."""
    lp = lock_path(path)
    lp.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows: a lock file whose process must be alive
        fcntl = None
    for _ in range(20):
        if fcntl is None:  # pragma: no cover
            try:
                fd = os.open(lp, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o644)
            except FileExistsError:
                who = holder(path) or {}
                if _pid_alive(who.get("pid")):
                    raise _busy(path, param) from None
                with contextlib.suppress(OSError):
                    os.unlink(lp)  # a dead process's: taken over
                continue
        else:
            fd = os.open(lp, os.O_CREAT | os.O_RDWR, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                if not wait:
                    os.close(fd)
                    raise _busy(path, param) from None
                print(f"waiting: {_busy(path, param)}", file=sys.stderr)
                fcntl.flock(fd, fcntl.LOCK_EX)  # until the other process is done with it
            try:  # the file may have been removed by its holder between open and lock: lock the new one
                if os.stat(lp).st_ino != os.fstat(fd).st_ino:
                    os.close(fd)
                    continue
            except FileNotFoundError:
                os.close(fd)
                continue
        doc = {"pid": os.getpid(), "host": socket.gethostname(), "command": _command(), "started": time.time()}
        os.ftruncate(fd, 0)
        os.write(fd, (json.dumps(doc) + "\n").encode())
        return fd
    raise _busy(path, param)  # pragma: no cover - the lock file kept changing under us


def _release(path, fd: int) -> None:
    with contextlib.suppress(OSError):
        os.unlink(lock_path(path))
    with contextlib.suppress(OSError):
        os.close(fd)


@contextlib.contextmanager
def lock(path, param: str = "--out", wait: bool = False):
    """Hold the exclusive lock of the output ``path`` for the block (re-entrant in one process);
    held elsewhere: refused (:class:`OutputBusy`), or with ``wait`` waited for."""
    key = _key(path)
    if key in _HELD:
        yield
        return
    fd = _acquire(path, param, wait)
    _HELD[key] = fd
    try:
        yield
    finally:
        _HELD.pop(key, None)
        _release(path, fd)


def held(path) -> bool:
    """Whether this process holds the lock of ``path`` (an outer command claimed it)."""
    return _key(path) in _HELD


# ------------------------------------------------------------------------------ the whole rule
@contextlib.contextmanager
def claim(path, *, kind: str = "folder", overwrite: bool = False, resume: bool = False, within=None,
          param: str = "--out", force_word: str = "--force"):
    """Check ``path`` (:func:`check_output`), lock it, remove the old output's files when
    ``overwrite``, and yield it; on a failure, a new run's files go again unless its folder holds a
    checkpoint to resume from. Nested claims of a path this
    process holds pass straight through (a command claims, the method it calls claims again)."""
    path = Path(path)
    if held(path):
        yield path
        return
    check_output(path, kind=kind, overwrite=overwrite, resume=resume, within=within, param=param,
                 force_word=force_word)
    made = _new_folders(Path(os.path.abspath(path)).parent)
    with lock(path, param), _remove_if_empty_on_failure(made):
        # checked again under the lock: another run may have finished there since
        check_output(path, kind=kind, overwrite=overwrite, resume=resume, within=within, param=param,
                     force_word=force_word)
        existed = os.path.lexists(path)
        if overwrite and existed and kind != "batch":
            clear(path)
        try:
            yield path
        except BaseException:
            after_failure(path, kind, resume, existed)
            raise


def _new_folders(folder: Path) -> list:
    """The folders, innermost first, that writing into ``folder`` creates."""
    made = []
    while not os.path.lexists(folder) and folder.parent != folder:
        made.append(folder)
        folder = folder.parent
    return made


@contextlib.contextmanager
def _remove_if_empty_on_failure(folders):
    """On a failure, the folders of ``folders`` (innermost first) left empty go again."""
    try:
        yield
    except BaseException:
        for folder in folders:
            try:
                folder.rmdir()
            except FileNotFoundError:
                continue
            except OSError:
                break
        raise


def after_failure(path: Path, kind: str, resume: bool, existed: bool) -> None:
    """A failed run: a folder with a checkpoint is kept (``--resume`` continues it); a new run's
    files go, so that running it again is not refused (the folder itself too, when the run made it)."""
    if kind != "folder" or resume or not path.is_dir() or (path / CHECKPOINT).is_file():
        return
    clear(path)
    if not existed:
        with contextlib.suppress(OSError):
            path.rmdir()
