"""Progress bars that suit where they are read.

On a terminal: tqdm's live bar. Anywhere else (a log file, a batch system's output, a pipe):
one plain line every :data:`LOG_SECONDS` seconds with the same figures (count, percent, elapsed,
remaining, rate and the latest values), and a last line at the end, instead of a frame with a
carriage return per refresh (a 30 000-iteration run would leave thousands of them in a log).
``CLGS_PROGRESS_SECONDS`` sets the interval.

One home for everything a run tells while it works (so one switch silences it all):

* :func:`progress_bar`: a bar over counted work (iterations, views, subjects);
* :func:`phase`: one line for a step that takes seconds without a count (loading a model, an FDK,
  a search): ``loading the shape model ... 2.1 s`` (on a terminal the time completes the line; in
  a log a start line and an end line);
* :func:`note`: a line of its own (the expected run time, say).

:func:`set_quiet` (the command line's ``--quiet``) silences all of them for the process;
:func:`enabled` (a method's ``progress=False``, ``--no-progress``) for the work inside it;
:func:`progress_enabled` says whether output is on here. Whatever is shown, or would be, also
goes to the listeners of :func:`listen` (a test, a notebook): events with the same figures.
"""
from __future__ import annotations

import contextlib
import contextvars
import os
import sys
import time

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


# ---------------------------------------------------------------------- the switch
_QUIET = False
_ENABLED = contextvars.ContextVar("clgs_progress_enabled", default=True)


def set_quiet(quiet: bool = True) -> None:
    """Silence (or restore) every bar, phase line and note of this process (``clgs --quiet``)."""
    global _QUIET  # noqa: PLW0603 - one process-wide switch
    _QUIET = bool(quiet)


def progress_enabled() -> bool:
    """Whether bars, phase lines and notes are shown here: not quiet (:func:`set_quiet`, or
    ``clgs --quiet``, which sets CLGS_VERBOSITY=quiet for this process and its workers), and no
    enclosing :func:`enabled` (False) turned them off."""
    return not _QUIET and _ENABLED.get() and os.environ.get("CLGS_VERBOSITY", "").strip().lower() != "quiet"


@contextlib.contextmanager
def enabled(flag: bool = True):
    """Within: progress shown only if ``flag`` and it was already on (a method's ``progress``
    argument; an inner True never overrides an outer False)."""
    token = _ENABLED.set(bool(flag) and _ENABLED.get())
    try:
        yield
    finally:
        _ENABLED.reset(token)


# ---------------------------------------------------------------------- listeners
_LISTENERS: list = []


@contextlib.contextmanager
def listen():
    """Within: every progress event is appended to the list yielded (dicts with ``event``:
    ``"phase"`` (``desc``, ``state`` "start"/"end", ``seconds`` at the end), ``"figures"``
    (``desc``, ``figures``: name -> value, ``final``), ``"note"`` (``text``)), whether shown or not."""
    events: list = []
    _LISTENERS.append(events)
    try:
        yield events
    finally:
        _LISTENERS.remove(events)


def emit(event: dict) -> None:
    """Hand ``event`` to the listeners (cheap when there are none)."""
    for events in _LISTENERS:
        events.append(dict(event))


def listening() -> bool:
    return bool(_LISTENERS)


# ---------------------------------------------------------------------- lines
_OPEN: list = []  # the phase whose terminal line waits for its time ("desc ... ")


def _stream(stream=None):
    return stream if stream is not None else sys.stderr


def _end_open_line() -> None:
    """Finish a phase's waiting terminal line before anything else is written."""
    if _OPEN:
        stream = _OPEN.pop()
        stream.write("\n")
        stream.flush()


def note(text: str, stream=None, bar=None) -> None:
    """One line (e.g. the expected run time), shown when progress is on; listeners get it always.
    ``bar``: a live bar of :func:`progress_bar` to clear first and redraw after."""
    emit({"event": "note", "text": text})
    if progress_enabled():
        _end_open_line()
        live = bar is not None and getattr(bar, "clgs_terminal", False)
        if live:
            bar.clear()
        out = _stream(stream)
        out.write(text + "\n")
        out.flush()
        if live:
            bar.refresh()


def format_seconds(seconds: float) -> str:
    """``0.076 s``, ``0.38 s``, ``2.4 s``, ``12 s``, ``3 min 5 s``, ``2 h 41 min``."""
    seconds = float(seconds)
    if seconds < 0.1:
        return f"{seconds:.3f} s"
    if seconds < 1:
        return f"{seconds:.2f} s"
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 60:
        return f"{seconds:.0f} s"
    m, sec = divmod(int(round(seconds)), 60)
    if m < 60:
        return f"{m} min {sec} s" if sec else f"{m} min"
    h, m = divmod(m, 60)
    return f"{h} h {m} min" if m else f"{h} h"


_DEPTH = contextvars.ContextVar("clgs_phase_depth", default=0)


@contextlib.contextmanager
def phase(desc: str, stream=None, clock=time.perf_counter):
    """One line for a step without a count: ``desc ...`` when it starts, its time when it ends
    (on a terminal the same line, unless something else was written meanwhile). A phase inside
    another, or under a bar, is part of it: listeners get its events, the screen only the outer
    line or the bar."""
    t0 = clock()
    emit({"event": "phase", "desc": desc, "state": "start"})
    show = progress_enabled() and _DEPTH.get() == 0 and not _LIVE_BARS
    out = _stream(stream)
    terminal = show and on_terminal(out)
    if show:
        _end_open_line()
        out.write(f"{desc} ..." + ("" if terminal else "\n"))
        out.flush()
        if terminal:
            _OPEN.append(out)
    token = _DEPTH.set(_DEPTH.get() + 1)
    try:
        yield
    finally:
        _DEPTH.reset(token)
        seconds = clock() - t0
        emit({"event": "phase", "desc": desc, "state": "end", "seconds": seconds})
        if show:
            if terminal and _OPEN and _OPEN[-1] is out:
                _OPEN.pop()
                out.write(f" {format_seconds(seconds)}\n")
            else:
                _end_open_line()
                out.write(f"{desc}: {format_seconds(seconds)}\n")
            out.flush()


def phased(desc: str):
    """Decorator: the function runs as a :func:`phase` named ``desc``."""
    import functools

    def wrap(fn):
        @functools.wraps(fn)
        def run(*args, **kwargs):
            with phase(desc):
                return fn(*args, **kwargs)

        return run

    return wrap


# ---------------------------------------------------------------------- bars
TERMINAL_NO_RATE = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}{postfix}]"
LOG_NO_RATE = "{desc}: {n_fmt}/{total_fmt} {unit} ({percentage:.0f}%), {elapsed} elapsed, {remaining} left{postfix}"


def progress_bar(iterable=None, rate: bool = True, **kwargs):
    """A tqdm bar (same arguments as ``tqdm``): live on a terminal, log lines elsewhere; off when
    :func:`progress_enabled` is False. ``rate=False``: no wall-clock rate on it (the caller shows
    its own figure, e.g. the training log's it/s)."""
    if not progress_enabled():
        kwargs["disable"] = True
    if not kwargs.get("disable"):
        _end_open_line()
    if not rate:
        kwargs.setdefault("bar_format", TERMINAL_NO_RATE if on_terminal(kwargs.get("file")) else LOG_NO_RATE)
    if on_terminal(kwargs.get("file")):
        from tqdm.auto import tqdm

        bar = _counted(tqdm)(iterable, **kwargs)
        bar.clgs_terminal = not kwargs.get("disable")
        return bar
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


_LIVE_BARS: set = set()  # ids of the bars shown and not yet closed (phases under them stay quiet)


def _counted(cls):
    """``cls`` (a tqdm class) whose shown instances are in :data:`_LIVE_BARS` until closed."""

    class Counted(cls):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            if not self.disable:
                _LIVE_BARS.add(id(self))

        def close(self):
            _LIVE_BARS.discard(id(self))
            super().close()

    return Counted


def _log_bar_class():
    """tqdm whose new figures wait for the next timed line instead of forcing one each."""
    from tqdm import tqdm

    class LogBar(_counted(tqdm)):
        def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
            super().set_postfix(ordered_dict, refresh=False, **kwargs)

        def set_description(self, desc=None, refresh=True):
            super().set_description(desc, refresh=False)

    return LogBar
