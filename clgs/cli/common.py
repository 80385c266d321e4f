"""What the CT commands (``clgs simulate``, ``clgs reconstruct``, ``clgs evaluate``) share:
their outputs' checks (never over the input, writable, ``--force`` to replace, empty folders
removed after a failure), reading volumes and scans with their errors as click errors, and the
way figures are printed. Only click and the standard library at module level."""
from __future__ import annotations

import math
import os
from pathlib import Path

import click

from clgs.io.suffixes import VOLUME_SUFFIXES
from clgs.limits import available_memory  # noqa: F401  (read here; tests patch it here)


def is_volume_path(path: Path) -> bool:
    name = path.name.lower()
    return any(name.endswith(s) for s in VOLUME_SUFFIXES)


def is_dicom_folder(path: Path) -> bool:
    """A folder holding DICOM slices (read as one series)."""
    return path.is_dir() and any(f.suffix.lower() == ".dcm" or f.name.upper().startswith(("IM", "CT"))
                                 for f in list(path.iterdir())[:50])


def _looks_like_scan(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and ((path / "scan.json").is_file() or (path / "meta_data.json").is_file()) \
        and not (path / "volume.npy").is_file() and not (path / "volume.nii.gz").is_file()


def _looks_like_result(path: Path) -> bool:
    path = Path(path)
    return (path.is_file() and is_volume_path(path) and not path.name.lower().startswith("truth.")) or \
        (path.is_dir() and ((path / "volume.npy").is_file() or (path / "volume.nii.gz").is_file()))


def check_evaluate_order(result, truth, usage: str) -> None:
    """Every ``evaluate`` takes the result first, then the truth (a volume or a scan folder): the
    old order (a scan folder first, a reconstruction second) is refused with the right one."""
    if result is not None and truth is not None and _looks_like_scan(Path(result)) \
            and _looks_like_result(Path(truth)):
        raise click.UsageError(f"{result} is a scan folder and {truth} a reconstruction: the arguments are the "
                               f"result first, then the truth ({usage}); swap them")


def click_error(exc: Exception, what: str = "") -> click.ClickException:
    msg = str(exc) if not what else f"{what}: {exc}"
    return click.ClickException(msg)


def check_output(path: Path, force: bool, param: str = "--out", kind: str | None = None, resume: bool = False) -> None:
    """The output rule of :mod:`clgs.io.outputs` (one home for every command) as a click error.
    ``kind``: ``file``, ``folder``, ``scan``; default: a file for a volume or a ``.json`` name."""
    from clgs.io.outputs import OutputError
    from clgs.io.outputs import check_output as rule

    if kind is None:
        kind = "file" if is_volume_path(path) or Path(path).suffix.lower() == ".json" else "folder"
    try:
        rule(path, kind=kind, overwrite=force, resume=resume, param=param)
    except OutputError as exc:
        raise click.ClickException(str(exc)) from None


def claim_output(path: Path, force: bool, kind: str | None = None, resume: bool = False, param: str = "--out"):
    """:func:`clgs.io.outputs.claim` (checks, the lock, ``--force`` clearing the old output) for a
    command's output; its refusals are click errors."""
    import contextlib

    from clgs.io.outputs import OutputError, claim

    if kind is None:
        kind = "file" if is_volume_path(path) else "folder"

    @contextlib.contextmanager
    def claimed():
        cm = claim(path, kind=kind, overwrite=force, resume=resume, param=param)
        try:
            cm.__enter__()
        except OutputError as exc:
            raise click.ClickException(str(exc)) from None
        try:
            yield path
        except BaseException:
            if not cm.__exit__(*__import__("sys").exc_info()):
                raise
        else:
            cm.__exit__(None, None, None)

    return claimed()


def nearest_existing(path: Path) -> Path:
    """``path`` or its closest ancestor that exists."""
    path = Path(os.path.abspath(path))
    while not os.path.lexists(path) and path.parent != path:
        path = path.parent
    return path


def check_writable(path: Path, param: str = "--out", into: bool = False) -> None:
    """Fail now, before any work, if ``path`` cannot be written: its folder (``into``: the folder
    ``path`` itself, written into) must exist or be creatable, be a folder, and accept new files.
    Tested by creating and removing an empty folder there (permission bits say nothing to root,
    nor on read-only or virtual file systems such as /proc)."""
    import tempfile

    from clgs.io.outputs import OutputError, check_names

    try:  # names too long for the file system (with the temporary names of atomic writes) fail now too
        check_names(path, param, folder=into or not (is_volume_path(path) or Path(path).suffix.lower() == ".json"))
    except OutputError as exc:
        raise click.ClickException(str(exc)) from None
    where = Path(path) if into else Path(os.path.abspath(path)).parent
    base = nearest_existing(where)
    if not base.is_dir():
        raise click.ClickException(f"cannot write {param} {path}: {base} is a file, not a folder; "
                                   f"choose another {param}")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".clgs-write-test-", dir=base))
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise click.ClickException(f"cannot write {param} {path}: files cannot be created in {base} ({reason}); "
                                   f"choose another {param}") from None


def new_folders(folder: Path) -> list:
    """The folders, innermost first, that writing into ``folder`` would create (none if it exists)."""
    folder = Path(os.path.abspath(folder))
    made = []
    while not os.path.lexists(folder) and folder.parent != folder:
        made.append(folder)
        folder = folder.parent
    return made


def remove_empty(folders) -> None:
    """Remove those of ``folders`` (innermost first) this command created and left empty; a folder
    holding anything (a checkpoint, a log, another program's files) is kept, and so are its parents."""
    for folder in folders:
        try:
            folder.rmdir()
        except FileNotFoundError:  # removed already (by the output's claim)
            continue
        except OSError:
            return


def scan_root(scan: Path):
    """The folder of the input scan (``scan`` may name its scan.json / meta_data.json), resolved."""
    scan = Path(scan)
    if scan.is_file() and scan.name in ("scan.json", "meta_data.json"):
        scan = scan.parent
    return scan.resolve() if scan.is_dir() else None


def scan_files(root: Path) -> list:
    """Every file and folder the scan in ``root`` is made of (resolved). A scan description that
    cannot be read protects everything in the folder."""
    import json

    found = []
    try:
        if (root / "scan.json").is_file():
            found += [root / "scan.json", root / "projections.npy", root / "truth.npy", root / "truth.nii.gz",
                      root / "truth_surface.stl"]
            doc = json.loads((root / "scan.json").read_text(encoding="utf-8"))
            found += [root / v for v in (doc.get("files") or {}).values() if isinstance(v, str)]
        if (root / "meta_data.json").is_file():
            found.append(root / "meta_data.json")
            doc = json.loads((root / "meta_data.json").read_text(encoding="utf-8"))
            found += [root / doc[k] for k in ("vol", "ct") if isinstance(doc.get(k), str)]
            for split in ("proj_train", "proj_test"):
                found += [root / str(e["file_path"]) for e in doc.get(split) or [] if isinstance(e, dict)
                          and "file_path" in e]
                found.append(root / split)
        if not found:
            found = list(root.iterdir())
    except (OSError, ValueError, TypeError, AttributeError):
        found = list(root.iterdir())
    return [f.resolve() for f in found]


def check_not_input(path: Path, inputs, param: str = "--out") -> None:
    """Refuse an output that is, contains, or would overwrite an input: ``inputs`` are
    (label, path, is_scan) -- a scan folder is protected as a whole and file by file."""
    target = Path(path).resolve()
    for label, given, is_scan in inputs:
        if given is None:
            continue
        if is_scan:
            root = scan_root(given)
            if root is None:
                continue
            if target == root:
                raise click.ClickException(f"{param} {path} is the input scan folder {given}; writing there would "
                                           f"replace the scan. Choose another {param}")
            if target in root.parents:
                raise click.ClickException(f"{param} {path} contains the input scan {given}; writing there would "
                                           f"delete the scan. Choose another {param}")
            for f in scan_files(root):
                if f == target or target in f.parents:
                    raise click.ClickException(f"{param} {path} would overwrite {f.name} of the input scan {given}. "
                                               f"Choose another {param}")
        else:
            src = Path(given).resolve()
            if target == src or target in src.parents:
                what = "is" if target == src else "contains"
                raise click.ClickException(f"{param} {path} {what} the input {label} {given}; writing there would "
                                           f"destroy it. Choose another {param}")


def out_of_memory(what: str, shape=None) -> click.ClickException:
    if shape is None:
        return click.ClickException(f"not enough memory {what}")
    n = math.prod(int(s) for s in shape)
    return click.ClickException(
        f"not enough memory {what}: the volume is {'x'.join(str(int(s)) for s in shape)} voxels "
        f"({n * 4 / 2 ** 30:.1f} GiB per float32 copy, and a method needs several); use a coarser grid "
        "(fewer voxels in the geometry's nVoxel) or a machine with more memory")




def check_memory(what: str, nbytes: float, hint: str) -> None:
    """Refuse, before any work, what would need more memory than the machine has now."""
    free = available_memory()
    if free is not None and nbytes > 0.9 * free:
        raise click.ClickException(f"{what} needs about {nbytes / 2**30:.3g} GiB of memory and {free / 2**30:.1f} GiB "
                                   f"are available; {hint}")


def is_out_of_memory(exc: BaseException) -> bool:
    """MemoryError, or torch's allocation failure (a RuntimeError)."""
    return isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and "can't allocate memory" in str(exc))


def load_volume_file(path: Path, spacing=None, label="volume", attenuation: bool = False, axes: str = "zyx",
                     doubt_negatives: bool = True):
    """(volume float32, spacing, origin) of a volume file, in the working (Z, Y, X) RAS+ order (a
    :class:`clgs.io.volume.LoadedVolume`: its ``orientation`` is the file's axis codes). With
    ``attenuation``, values whose kind cannot be attenuation are refused (complex, boolean masks)
    or warned about (integers; values no tissue has, negatives below -0.01/mm unless not
    ``doubt_negatives``). ``axes``: the order of a ``.npy`` array's axes, ``zyx`` (clgs's) or
    ``xyz`` (R2-Gaussian's ``vol_gt.npy``); files that carry their own orientation ignore it."""
    import numpy as np

    from clgs.io.volume import LoadedVolume, VolumeError, load_volume

    if not (is_volume_path(path) or is_dicom_folder(path)):
        raise click.BadParameter(f"{path}: a {label} must be {', '.join(VOLUME_SUFFIXES)} or a folder of DICOM "
                                 "slices", param_hint=label.upper())
    try:
        loaded = load_volume(path, dtype=None)
    except VolumeError as exc:
        raise click_error(exc) from None
    vol, sp, org = loaded
    if axes not in ("zyx", "xyz"):
        raise click.BadParameter(f"{axes!r}: give zyx or xyz", param_hint="--axes")
    if axes == "xyz" and str(path).lower().endswith(".npy"):
        vol = np.ascontiguousarray(vol.transpose(2, 1, 0))
    if attenuation:
        if np.issubdtype(vol.dtype, np.complexfloating):
            raise click.ClickException(f"{path}: complex values (dtype {vol.dtype}); attenuation is real: give "
                                       "the magnitude or the real part")
        if vol.dtype == bool or (np.issubdtype(vol.dtype, np.integer) and vol.size and int(vol.max()) <= 1
                                 and int(vol.min()) >= 0):
            raise click.ClickException(f"{path}: a mask (values 0 and 1 only, dtype {vol.dtype}), not attenuation; "
                                       "give attenuation in 1/mm (e.g. a mask times 0.02 for soft tissue)")
        if np.issubdtype(vol.dtype, np.integer):
            click.echo(f"warning: {path} holds integers (dtype {vol.dtype}): read as attenuation in 1/mm; for "
                       "Hounsfield units add --hu, for labels give attenuation instead", err=True)
        from clgs.io.units import attenuation_doubt

        doubt = attenuation_doubt(vol, negatives=doubt_negatives)
        if doubt is not None:
            click.echo(f"warning: {path}: {doubt}", err=True)
    vol = np.asarray(vol, np.float32)
    if spacing is not None:
        sp = tuple(float(s) for s in spacing)
    return LoadedVolume(vol, sp, org, loaded.orientation)


def parse_spacing(value, param: str = "--spacing"):
    """'d' or 'dZ,dY,dX' (mm) -> three positive numbers, or None."""
    if value is None:
        return None
    parts = [p for p in value.replace(",", " ").split() if p]
    try:
        nums = [float(p) for p in parts]
    except ValueError:
        raise click.BadParameter(f"{value!r}: give one number or three (dZ,dY,dX) in mm", param_hint=param) from None
    if len(nums) == 1:
        nums *= 3
    if len(nums) != 3 or min(nums) <= 0 or not all(math.isfinite(n) for n in nums):
        raise click.BadParameter(f"{value!r}: give one positive number or three (dZ,dY,dX) in mm",
                                 param_hint=param)
    return tuple(nums)


def fmt_number(value) -> str:
    return "inf" if isinstance(value, float) and math.isinf(value) else f"{value:.4f}"


def load_scan(path: Path, split: str = "train"):
    """Scan.load with its errors as click errors and its repairs (ScanWarning) as messages."""
    import warnings

    from clgs.io.scan import Scan, ScanError, ScanWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ScanWarning)
        try:
            sc = Scan.load(path, split=split)
        except ScanError as exc:
            raise click_error(exc) from None
    for w in caught:
        if issubclass(w.category, ScanWarning):
            click.echo(f"warning: {w.message}", err=True)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return sc


def exit_if_interrupted(info) -> None:
    """After an interrupted run wrote what it had: exit with 128 + the signal's number (130 for
    Ctrl-C, 143 for SIGTERM), as shells and batch systems expect, so that ``... && next`` stops."""
    if isinstance(info, dict) and info.get("interrupted"):
        import signal

        sig = int(info.get("stop_signal") or signal.SIGINT)
        click.echo(f"interrupted by {signal.Signals(sig).name}: the outputs so far are written; "
                   "the same command with --resume continues the run", err=True)
        raise SystemExit(128 + sig)
