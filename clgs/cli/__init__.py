"""The ``clgs`` command line: a click group whose commands are imported only when run.

Commands live in the modules beside this one; anatomy plugins add one group each (see ``clgs.anatomy.plugins``).
Nothing heavy (torch, pyopencl) is imported to print ``clgs --help``: commands import the
library when they run.

May import every layer; nothing imports it.
"""
from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os

import click

from clgs.commands import BUILTIN_COMMANDS
from clgs.errors import ClgsError

# name -> "module:attribute" of a click command, imported on first use
COMMANDS = BUILTIN_COMMANDS


def _load(target: str) -> click.Command:
    module, attr = target.split(":")
    return getattr(importlib.import_module(module), attr)


@contextlib.contextmanager
def clgs_errors_as_messages():
    """The one place where the library's errors (:class:`clgs.errors.ClgsError`) become click
    errors: the message, no traceback, exit status 1."""
    try:
        yield
    except ClgsError as exc:
        raise click.ClickException(str(exc) or type(exc).__name__) from exc


class LazyGroup(click.Group):
    """Lists built-in commands and one group per installed anatomy plugin, importing lazily.
    Every command runs under :func:`clgs_errors_as_messages`, listing the plugins (for
    ``--help``) included."""

    def make_context(self, info_name, args, parent=None, **extra):
        with clgs_errors_as_messages():
            return super().make_context(info_name, args, parent=parent, **extra)

    def invoke(self, ctx):
        try:
            with clgs_errors_as_messages():
                return super().invoke(ctx)
        except KeyboardInterrupt:  # a second Ctrl-C, or one outside a run's own handling
            click.echo("interrupted (Ctrl-C): stopped at once; outputs are written whole or not at all", err=True)
            ctx.exit(130)

    def _anatomy_names(self):
        try:
            from clgs.anatomy import plugins
        except ImportError:
            return []
        plugins.registry().add_commands(self)  # plugins' own commands (hook register_commands), once
        return plugins.anatomy_names()

    def list_commands(self, ctx):
        self._anatomy_names()
        names = {n for n, t in COMMANDS.items() if importlib.util.find_spec(t.split(":")[0])}
        names |= set(super().list_commands(ctx))
        names |= set(self._anatomy_names())
        return sorted(names)

    def get_command(self, ctx, name):
        if name in COMMANDS:
            return _load(COMMANDS[name])
        self._anatomy_names()
        cmd = super().get_command(ctx, name)
        if cmd is not None:
            return cmd
        if name in self._anatomy_names():
            from clgs.anatomy import plugins
            from clgs.cli.anatomy_group import make_group

            return make_group(plugins.get_anatomy(name))
        return None


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="clgs")
@click.option("--device", "device", metavar="SPEC", default=None,
              help="OpenCL device to run on: P:D indices or a piece of its name (pocl, intel, nvidia), "
                   "as 'clgs info' lists them. Default: the first device that passes the probe "
                   "(CLGS_DEVICE or PYOPENCL_CTX set it too).")
@click.option("--quiet", "-q", is_flag=True,
              help="say only errors, warnings and the result (what was written, the figures): no progress bars")
@click.option("--verbose", "-v", is_flag=True, help="say more: the device, the settings a run uses, timings")
@click.pass_context
def main(ctx, device, quiet, verbose):
    """clgs: sparse-view X-ray 3D reconstruction with Gaussian splatting and shape priors.

    Kernels run in OpenCL (PoCL or Intel's runtime on the CPU, or any OpenCL GPU). Each
    installed anatomy plugin adds a command group (e.g. ``clgs femur demo``). Every command
    follows one convention: -o/--out where it writes, --set KEY=VALUE for settings, --force to
    overwrite existing outputs (docs/commands.md).
    """
    from clgs.cli.verbosity import set_level

    if quiet and verbose:
        raise click.UsageError("give --quiet or --verbose, not both")
    if quiet or verbose:
        set_level(ctx, "quiet" if quiet else "verbose")
    _plain_warnings()
    # torch's OpenMP threads spin for a while after every parallel op by default and starve PoCL's
    # worker threads on the same cores (a 32^3 voxelizer block: 22-325 ms with spinning, 6-7 ms
    # without); ask them to sleep. Read when torch loads: set before any command imports it.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if device is not None:
        if not device.strip():
            raise click.BadParameter("give a device index (P:D) or a piece of its name", param_hint="--device")
        # an environment variable, so that subprocesses and cluster workers use the same device
        os.environ["CLGS_DEVICE"] = device.strip()


def _plain_warnings() -> None:
    """clgs's own warnings (about the user's scan, settings or result) print as ``Category: text``:
    the source line Python would name is in clgs, sometimes generated code (``<string>:8``), and
    says nothing to the user. Other packages' warnings keep Python's form."""
    import warnings

    default = warnings.formatwarning
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def fmt(message, category, filename, lineno, line=None):
        ours = (getattr(category, "__module__", "").startswith("clgs") or str(filename).startswith("<")
                or os.path.abspath(str(filename)).startswith(here + os.sep))
        if ours:
            return f"{category.__name__}: {message}\n"
        return default(message, category, filename, lineno, line)

    warnings.formatwarning = fmt


if __name__ == "__main__":  # pragma: no cover
    main()
