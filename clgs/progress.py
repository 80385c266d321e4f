"""Progress bars that suit where they are read.

On a terminal: tqdm's live bar. Anywhere else (a log file, a batch system's output, a pipe):
one plain line every :data:`LOG_SECONDS` seconds with the same figures (count, percent, elapsed,
remaining, rate and the latest values), and a last line at the end, instead of a frame with a
carriage return per refresh (a 30 000-iteration run would leave thousands of them in a log).
``CLGS_PROGRESS_SECONDS`` sets the interval.
"""
from __future__ import annotations

import os
import sys

LOG_SECONDS = 10.0
LOG_FORMAT = ("{desc}: {n_fmt}/{total_fmt} {unit} ({percentage:.0f}%), {elapsed} elapsed, {remaining} left, "
              "{rate_fmt}{postfix}")


class LogLines:
    """A stream for tqdm that writes each refresh as one whole line (no carriage returns)."""

    def __init__(self, stream):
        self.stream = stream
        self.last = None

    def write(self, text: str) -> None:
        line = text.replace("\r", "").strip()
        if line and line != self.last:  # closing repeats the final refresh
            self.stream.write(line + "\n")
            self.last = line

    def flush(self) -> None:
        self.stream.flush()


def log_seconds() -> float:
    try:
        value = float(os.environ.get("CLGS_PROGRESS_SECONDS", LOG_SECONDS))
    except ValueError:
        return LOG_SECONDS
    return value if value > 0 and value == value else LOG_SECONDS


def on_terminal(stream=None) -> bool:
    stream = stream if stream is not None else sys.stderr
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_enabled() -> bool:
    """False under ``clgs --quiet`` (CLGS_VERBOSITY=quiet): no bar, whatever the caller asked."""
    return os.environ.get("CLGS_VERBOSITY", "").strip().lower() != "quiet"


def progress_bar(iterable=None, **kwargs):
    """A tqdm bar (same arguments as ``tqdm``): live on a terminal, log lines elsewhere."""
    if not progress_enabled():
        kwargs["disable"] = True
    if on_terminal(kwargs.get("file")):
        from tqdm.auto import tqdm

        return tqdm(iterable, **kwargs)
    if kwargs.get("disable"):
        from tqdm import tqdm

        return tqdm(iterable, **kwargs)
    kwargs.pop("dynamic_ncols", None)
    kwargs["file"] = LogLines(kwargs.get("file") or sys.stderr)
    kwargs.setdefault("mininterval", log_seconds())
    kwargs.setdefault("maxinterval", max(log_seconds(), 10.0))
    kwargs.setdefault("bar_format", LOG_FORMAT)
    kwargs.setdefault("unit", "it")
    kwargs["leave"] = True  # the last line stays in the log
    return _log_bar_class()(iterable, **kwargs)


def _log_bar_class():
    """tqdm whose new figures wait for the next timed line instead of forcing one each."""
    from tqdm import tqdm

    class LogBar(tqdm):
        def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
            super().set_postfix(ordered_dict, refresh=False, **kwargs)

        def set_description(self, desc=None, refresh=True):
            super().set_description(desc, refresh=False)

    return LogBar
