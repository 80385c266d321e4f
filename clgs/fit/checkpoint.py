"""Training checkpoints: everything a run needs to continue bit for bit, and nothing executable.

A checkpoint is one ``torch.save`` file holding only tensors, numbers, strings, lists and dicts
(so it loads with ``torch.load(weights_only=True)``): the raw parameters of every Gaussian set,
Adam's state, the densifier's accumulators, the torch and NumPy generator states, the iteration,
the remaining view order and the log so far. Non-tensor structures that need exact round trips
(NumPy's 128-bit generator state, the log rows) travel as JSON strings. The file is written
atomically (temporary sibling + rename), so a crash while saving keeps the previous checkpoint.
"""
from __future__ import annotations

import io
import json
from pathlib import Path

import torch

from clgs.errors import ClgsError
from clgs.io import atomic

FORMAT = "clgs-checkpoint-1"


class CheckpointError(ClgsError, ValueError):
    """A checkpoint that does not belong to this run or cannot be read."""


def save(path, state: dict) -> Path:
    """Write ``state`` (tensors, numbers, strings, lists, dicts) to ``path`` atomically."""
    state = dict(state)
    state["format"] = FORMAT
    buf = io.BytesIO()
    torch.save(state, buf)
    return atomic.write_bytes(path, buf.getvalue())


def load(path) -> dict:
    """Read a checkpoint written by :func:`save` (``weights_only=True``: no code is run)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}; start without --resume, or point to the run's folder")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - report any unpickling failure the same way
        # torch's own message suggests weights_only=False, which would run whatever the file holds:
        # never pass that advice on
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if "weights_only" in first or "WeightsUnpickler" in first:
            first = "it holds objects other than tensors and plain data"
        raise CheckpointError(f"{path} is not a readable clgs checkpoint ({first}); it is damaged or was not made "
                              "by clgs: delete it, or start the run again without --resume. clgs never loads "
                              "a checkpoint in a way that could run code from it") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        found = state.get("format") if isinstance(state, dict) else "?"
        raise CheckpointError(f"{path} is not a clgs checkpoint (format {found})")
    return state


def dumps(obj) -> str:
    return json.dumps(obj)


def loads(text: str):
    return json.loads(text)
