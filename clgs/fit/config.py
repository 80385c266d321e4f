"""The settings every Gaussian reconstruction shares, and how a run gets them.

:class:`JsonConfig` gives a method's settings (a dataclass) a checked JSON round trip;
:class:`GaussianFitConfig` holds R2-Gaussian's defaults for what every Gaussian method has (loss
weights, FDK-based initialisation, densification, scale bounds, projector, logging);
:func:`run_config` gives a new run its settings or a resumed run its checkpoint's.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import ClassVar

import numpy as np

from clgs.errors import InputError
from clgs.fit import checkpoint as ckpt
from clgs.io.outputs import OutputError, claim
from clgs.limits import MAX_ITERATIONS

CHECKPOINT = "checkpoint.pt"  # the file name of a run's checkpoint in its folder


def setting(default, flag: str | None = None, help: str = "", **cli):
    """A settings field with its default; ``flag`` (e.g. ``"--tv"``) and ``help`` make it a
    command-line option (:mod:`clgs.cli.options`), ``cli`` may add ``min``, ``max``, ``max_open``
    beyond what the config's own checks say."""
    meta = {} if flag is None else {"flag": flag, "help": help, **cli}
    return field(default=default, metadata=meta)


class JsonConfig:
    """JSON round trip of a method's settings (a dataclass); unknown keys and values of the wrong
    kind or out of range are a clear error (checked when the settings are made)."""

    KIND = "method"
    CLI: tuple = ()  # the fields offered on the command line (each has a flag in its metadata)
    CHOICES: dict = {}  # setting -> allowed strings
    POSITIVE: frozenset = frozenset()  # numbers that must be > 0 (every number must be >= 0)
    AT_LEAST: dict = {}  # setting -> smallest allowed value
    AT_MOST: dict = {"iterations": MAX_ITERATIONS, "schedule_iterations": MAX_ITERATIONS}  # -> largest allowed

    def __post_init__(self):
        for f in fields(self):
            setattr(self, f.name, self._checked(f.name, str(f.type), getattr(self, f.name)))

    def _checked(self, name: str, kind: str, value):
        where = f"{self.KIND} setting {name}"
        if value is None:
            if "None" in kind:
                return None
            raise InputError(f"{where} must be given (got null)")
        base = kind.split("|")[0].strip()
        if base == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise InputError(f"{where} must be true or false, got {value!r}")
            return bool(value)
        if base == "str":
            if not isinstance(value, str):
                raise InputError(f"{where} must be a string, got {value!r}")
            allowed = self.CHOICES.get(name)
            if allowed and value not in allowed:
                raise InputError(f"{where} must be one of {', '.join(allowed)}, got {value!r}")
            return value
        if base == "tuple":
            return value
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise InputError(f"{where} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise InputError(f"{where} must be finite, got {value!r}")
        if base == "int":
            if value != int(value):
                raise InputError(f"{where} must be a whole number, got {value!r}")
            value = int(value)
        else:
            value = float(value)
        low, high = self.AT_LEAST.get(name, 0), self.AT_MOST.get(name)
        if high is not None and not low <= value <= high:
            raise InputError(f"{where} must be between {low:,} and {high:,}, got {value!r}")
        if value < low or (name in self.POSITIVE and value <= 0):
            need = "> 0" if name in self.POSITIVE else f">= {low:g}"
            raise InputError(f"{where} must be {need}, got {value!r}")
        return value

    def to_json(self) -> dict:
        d = asdict(self)
        if d.get("scale_bounds") is not None:
            d["scale_bounds"] = list(d["scale_bounds"])
        return d

    @classmethod
    def from_json(cls, d: dict):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"unknown {cls.KIND} settings: {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        d = dict(d)
        if d.get("scale_bounds") is not None:
            d["scale_bounds"] = tuple(d["scale_bounds"])
        return cls(**d)


@dataclass
class GaussianFitConfig(JsonConfig):
    """Settings every Gaussian reconstruction shares (R2-Gaussian's defaults): loss weights,
    FDK-based initialisation, densification, scale bounds, the projector and the run's logging."""

    iterations: int = setting(30_000, "--iterations", "training iterations (one view each)", max=MAX_ITERATIONS)
    init_threshold: float = 0.05  # of the FDK range
    density_factor: float = 0.15
    lambda_dssim: float = setting(0.25, "--dssim", "weight of the D-SSIM term")
    lambda_tv: float = setting(0.05, "--tv", "weight of the TV term (0 disables it)")
    tv_size: int = 32
    tv_every: int = 1  # the TV patch every k-th iteration, weighted k times (1: every iteration, as published)
    densify_start: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    grad_threshold: float = 5e-5
    densify_scale_threshold: float = 0.1  # of the volume extent: at most this -> clone, else split
    min_density: float = 1e-5
    max_gaussians: int = setting(500_000, "--max-gaussians", "cap on the number of Gaussians while densifying")
    scale_bounds: tuple | None = (0.0005, 0.5)  # of the volume extent; None -> exp scales
    # smallest scale >= this x the scan's resolution (None: off)
    scale_floor: float | None = setting(0.4, "--scale-floor",
                                        "smallest Gaussian scale as a fraction of the scan's resolution (voxel or "
                                        "detector pixel at the axis); 0 keeps only R2-Gaussian's 0.05 % of the volume")
    # "affine" (R2-Gaussian) | "exact"
    projector_mode: str = setting("affine", "--projector",
                                  "R2-Gaussian's affine splat or the exact ray integral")
    backend: str = setting("cl", "--backend", "OpenCL kernels or the plain torch reference")
    seed: int = setting(0, "--seed", "random seed")
    value_scale: float | None = None  # None -> 1 / p99.9 of the FDK volume
    log_every: int = setting(500, "--log-every", "evaluate and log every N iterations")
    log_early: bool = setting(True, "--log-early",
                              "also evaluate at iterations 10, 20, 50, 100, 200, ... below the first --log-every, "
                              "where the error falls fastest")
    checkpoint_every: int = setting(1000, "--checkpoint-every",
                                    "write a checkpoint every N iterations (0: only at the end / on Ctrl-C)")
    schedule_iterations: int | None = None  # length of the lr decays (default: iterations)
    lr_factor: float = 1.0  # every learning rate of R2-Gaussian's schedules (the free Gaussians) times this
    # how the run spends its iterations (clgs.fit.schedule): "fast" (the default run) or "paper";
    # the fields above hold the paper's values, a run gets its schedule's from run_config
    schedule: str = setting("fast", "--schedule",
                            "fast: the paper's schedule cut short (the method's fast length, or --iterations; the "
                            "shape-guided method also stops once its projections stop improving); paper: the "
                            "published 30 000 iterations")
    # the plateau rule (clgs.fit.schedule.PlateauStop): checks every stop_every iterations after
    # densification (0: off; None: the schedule's: the fast schedule's FAST_STOP_EVERY, paper off)
    stop_every: int | None = None
    stop_tolerance: float = 0.002  # relative fall of the loss on every view between checks, below: flat
    stop_patience: int = 2  # flat checks in a row that end the run
    # coarse-to-fine rendering (clgs.fit.schedule.CoarseToFine): this fraction of the run on a
    # detector binned by coarse_factor (0: full resolution throughout)
    coarse_until: float = 0.0
    coarse_factor: int = 2
    # views rendered per iteration: their projection losses averaged, one TV patch and one Adam
    # step for all of them (R2-Gaussian: 1; docs/schedules.md measures more)
    views_per_step: int = setting(1, "--views-per-step",
                                  "views rendered per iteration, their projection losses averaged under one TV patch "
                                  "and one Adam step (R2-Gaussian: 1; at most the number of views)")

    FAST_ITERATIONS = 30_000  # the fast schedule's run length (each method sets its own)
    FAST_STOP_EVERY = 500  # the fast schedule's plateau checks
    FAST_SETTINGS = {}  # settings the fast schedule changes from the paper's (each method sets its own)
    # ... and on scans of at least MANY_VIEWS views (may hold its own "iterations": the run's length)
    FAST_MANY_VIEWS: ClassVar[dict] = {}
    MANY_VIEWS = 20

    CHOICES = {"projector_mode": ("affine", "exact"), "backend": ("cl", "torch"), "schedule": ("fast", "paper")}
    POSITIVE = frozenset({"value_scale", "lr_factor"})
    AT_LEAST = {"iterations": 1, "densify_interval": 1, "max_gaussians": 1, "tv_size": 2, "tv_every": 1,
                "schedule_iterations": 1, "stop_patience": 1, "coarse_factor": 1, "views_per_step": 1}
    AT_MOST = {**JsonConfig.AT_MOST, "coarse_until": 1.0}

    def __post_init__(self):
        super().__post_init__()
        b = self.scale_bounds
        if b is not None:
            try:
                lo, hi = (float(x) for x in b)
            except (TypeError, ValueError):
                raise InputError(f"{self.KIND} setting scale_bounds must be two numbers (or null), got {b!r}") from None
            if not (0 < lo < hi and math.isfinite(hi)):
                raise InputError(f"{self.KIND} setting scale_bounds must satisfy 0 < low < high, got {b!r}")
            self.scale_bounds = (lo, hi)


# A run's output folder that would lose work or overwrite its input (the rule of clgs.io.outputs).
RunFolderError = OutputError


def run_folder(out_dir, resume: bool = False, overwrite: bool = False):
    """The run folder of a Python call (:func:`clgs.io.outputs.claim`): refused when it holds
    anything, unless ``resume`` (continue its run) or ``overwrite`` (replace it: its clgs files go
    first); locked while the run writes it. Nothing to claim without ``out_dir``."""
    import contextlib

    if out_dir is None:
        return contextlib.nullcontext()
    return claim(out_dir, kind="folder", overwrite=overwrite, resume=resume, param="out_dir",
                 force_word="overwrite=True")


def check_run_folder(out_dir, resume: bool) -> None:
    """Refuse an ``out_dir`` that is a scan folder (the run's files would land among the scan's),
    and one that holds another run (its checkpoint) unless that run is being resumed: a new run
    there would replace it. Delete the old run's folder, or choose another, to start afresh."""
    if out_dir is None:
        return
    out = Path(out_dir)
    for folder in (out, *out.resolve().parents):
        if (folder / "scan.json").is_file() or (folder / "meta_data.json").is_file():
            where = "is" if folder == out else f"lies inside {folder}, which is"
            raise RunFolderError(f"{out} {where} a scan folder: a run's outputs may not go into its input; "
                                 "choose another output folder")
    if not resume and (out / CHECKPOINT).is_file():
        raise RunFolderError(f"{out} holds a run already ({CHECKPOINT}); resume it (--resume, resume=True), "
                             "or delete that folder (or pass --force on the command line) to start a new run there")


def run_config(config_cls, iterations: int | None, settings: dict, resume: bool, out_dir,
               n_views: int | None = None):
    """(settings, checkpoint or None) of a new run, or of a run resumed from ``out_dir``: a resumed
    run keeps its checkpoint's settings (only ``iterations`` may grow and ``backend`` change).

    ``iterations=None``: the schedule's length for a new run (:func:`clgs.fit.schedule.resolve`:
    30 000 for ``schedule="paper"``, the method's shorter run for ``"fast"``); for a resumed one,
    the iterations it was started with (an interrupted run is finished, not extended). ``n_views``:
    the scan's training views, for a fast schedule that differs on many views (R2-Gaussian mode)."""
    if iterations is not None and not 1 <= iterations <= MAX_ITERATIONS:
        raise InputError(f"iterations must be between 1 and {MAX_ITERATIONS:,}, got {iterations}")
    check_run_folder(out_dir, resume)
    settings = dict(settings)
    if not resume:
        from clgs.fit.schedule import resolve

        cfg = config_cls.from_json(resolve(config_cls, iterations, settings, n_views))
        if n_views is not None:  # refused before the start's FDK, not after it
            from clgs.fit.trainer import check_views_per_step

            check_views_per_step(getattr(cfg, "views_per_step", 1), n_views)
        return cfg, None
    if out_dir is None:
        raise InputError("resume needs out_dir (the folder holding checkpoint.pt)")
    state = ckpt.load(Path(out_dir) / CHECKPOINT)
    try:
        saved = ckpt.loads(state["config"])
        if not isinstance(saved, dict):
            raise TypeError(type(saved).__name__)
    except (KeyError, TypeError, ValueError) as exc:
        raise ckpt.CheckpointError(f"{Path(out_dir) / CHECKPOINT} holds no readable run settings ({exc}): it "
                                   "cannot be resumed; start a new run") from None
    if "schedule" not in saved:  # written before schedules existed: it ran the paper's, to its end
        saved.update(schedule="paper", stop_every=0)
    if "scale_floor" not in saved and any(f.name == "scale_floor" for f in fields(config_cls)):
        saved["scale_floor"] = None  # written before the floor existed: keep the bounds it trained with
    cfg = config_cls.from_json(saved)
    cfg.schedule_iterations = cfg.schedule_iterations or cfg.iterations
    planned = cfg.iterations if iterations is None else int(iterations)
    cfg.iterations = max(planned, int(state["iteration"]))
    if "backend" in settings:  # where to compute does not change the run's meaning
        cfg.backend = settings.pop("backend")
    if settings:
        raise InputError(f"resume continues with the checkpoint's settings; drop {', '.join(sorted(settings))}")
    return cfg, state
