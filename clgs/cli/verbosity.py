"""How much the commands say: ``clgs --quiet`` / ``clgs --verbose`` (the root group's options).

quiet    errors, warnings and each command's result lines (what it wrote, its figures); no
         announcements, no progress bars
normal   those, plus announcements (what is about to run) and progress bars
verbose  those, plus detail: the device, the settings a run uses, timings

Held in the environment (``CLGS_VERBOSITY``), so that progress bars anywhere in the library
(:func:`clgs.progress.progress_enabled`), subprocesses and local cluster workers follow it.
"""
from __future__ import annotations

import os

import click

ENV = "CLGS_VERBOSITY"
LEVELS = ("quiet", "normal", "verbose")


def level() -> str:
    value = os.environ.get(ENV, "normal").strip().lower()
    return value if value in LEVELS else "normal"


def set_level(ctx: click.Context, value: str) -> None:
    """Set the level for this command (restored when the command's context closes)."""
    before = os.environ.get(ENV)
    os.environ[ENV] = value

    def restore():
        if before is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = before

    ctx.call_on_close(restore)


def is_quiet() -> bool:
    return level() == "quiet"


def is_verbose() -> bool:
    return level() == "verbose"


def info(message: str, err: bool = True) -> None:
    """An announcement (not a result): said unless ``--quiet``."""
    if not is_quiet():
        click.echo(message, err=err)


def detail(message: str) -> None:
    """Detail for ``--verbose`` only (on stderr)."""
    if is_verbose():
        click.echo(message, err=True)


def result(message: str) -> None:
    """A result line (what was written, the figures): always said."""
    click.echo(message)
