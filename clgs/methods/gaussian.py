"""What the Gaussian methods (:mod:`.r2gs`, :mod:`.shape_guided`) share as methods: the options
of a run that are not settings, and the dictionary a run hands back to the command line."""
from __future__ import annotations

import sys

from clgs.methods import Option

RUN_OPTIONS = [
    Option("--resume", "resume", "flag", "continue the run in --out from its checkpoint (bit for bit)"),
    Option("--progress", "progress", "switch", "show a progress bar"),
]


def method_output(result, out_dir, files: dict, **extra) -> dict:
    """``{"volume", "files", "info", "result"}`` of a finished (or interrupted) run; its summary, and how to
    continue an interrupted one, go to stderr. ``extra``: more figures for the report."""
    print(result.summary, file=sys.stderr)
    if result.interrupted:
        what = (f"outputs so far written; continue with --resume --out {out_dir}" if out_dir is not None
                else "nothing written (the run has no output folder)")
        print(f"interrupted at iteration {result.trainer.iteration}: {what}", file=sys.stderr)
    info = {"iterations": result.trainer.iteration, "n_gaussians": result.trainer.n_gaussians,
            "training_seconds": result.trainer.seconds, "value_scale": result.value_scale,
            "interrupted": result.interrupted, "stop_signal": getattr(result.trainer, "stop_signal", None),
            # the schedule, and where its plateau rule ended the run (None: it ran every iteration)
            "schedule": result.trainer.config.get("schedule"),
            # an iteration's views and the learning rates' factor (the fast schedule raises both on
            # many views), so "iterations" is read right
            "views_per_step": result.trainer.views_per_step,
            "lr_factor": result.trainer.config.get("lr_factor"),
            "converged": getattr(result.trainer, "converged", None), **extra}
    # "result": the method's whole result (log, trainer), for Python callers such as the experiment
    return {"volume": result.volume, "files": files, "info": info, "result": result}
