"""Command-line options of the reconstruction methods, made in one place.

A method says what it takes as data (:class:`clgs.methods.Option` records, and the fields of its
settings dataclass that carry a ``flag`` in their metadata, see :func:`clgs.fit.config.setting`);
this module turns them into click options: the type, range and choices come from the field's
type and its config's ``CHOICES`` / ``POSITIVE`` / ``AT_LEAST``, the ``[default: ...]`` in the
help from the field's default, so nothing is written twice.

Option types: click's ``float`` and ``FloatRange`` accept ``nan`` and ``inf`` (NaN passes every
range check), which end as a NumPy error deep in a run; :class:`FiniteFloat` refuses them at
parse time, and :class:`Seed` takes random seeds (0 to 2**64 - 1), the one seed type of every
command. :func:`check_option_values` applies the same rules to values parsed by any method's
options (whatever type they declared), so a non-finite float or a negative seed is refused before
a run starts.
"""
from __future__ import annotations

import dataclasses
import math

import click

from clgs.methods import Method, Option

SEED_MAX = 2 ** 64 - 1  # torch.Generator.manual_seed's upper bound; NumPy takes any non-negative integer


class FiniteFloat(click.FloatRange):
    """A float option that refuses NaN and +-inf, optionally bounded like :class:`click.FloatRange`
    (``FiniteFloat(min=0)``, ``FiniteFloat(0, 2, min_open=True, max_open=True)``). ``hint`` is
    added to the message when a value is refused (e.g. why the bound is there)."""

    def __init__(self, min=None, max=None, min_open: bool = False, max_open: bool = False, hint: str = ""):
        super().__init__(min=min, max=max, min_open=min_open, max_open=max_open)
        self.name = "float" if min is None and max is None else "float range"
        self.hint = hint

    def _describe_range(self) -> str:
        if self.min is None and self.max is None:
            return ""
        return super()._describe_range()

    def _with_hint(self, message: str) -> str:
        return f"{message.rstrip('.')} ({self.hint})" if self.hint else message

    def convert(self, value, param, ctx):
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(self._with_hint(f"{value!r} is not a number"), param, ctx)
        if not math.isfinite(number):
            rng = self._describe_range()
            self.fail(self._with_hint(f"{value!r} is not a finite number; give a finite value"
                                      + (f" in the range {rng}" if rng else "")), param, ctx)
        try:
            return super().convert(number, param, ctx)
        except click.BadParameter as exc:
            exc.message = self._with_hint(exc.message)
            raise


class Seed(click.ParamType):
    """A random seed: an integer from 0 to 2**64 - 1 (what both NumPy and torch accept)."""

    name = "integer"

    def convert(self, value, param, ctx):
        if isinstance(value, bool):
            self.fail(f"{value!r} is not a valid seed", param, ctx)
        try:
            number = int(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a valid seed: give an integer from 0 to 2**64 - 1", param, ctx)
        if isinstance(value, float) and number != value:
            self.fail(f"{value!r} is not a valid seed: give an integer from 0 to 2**64 - 1", param, ctx)
        if not 0 <= number <= SEED_MAX:
            self.fail(f"{number} is not a valid seed: give an integer from 0 to 2**64 - 1", param, ctx)
        return number


def _values(value):
    if isinstance(value, (list, tuple)):
        for v in value:
            yield from _values(v)
    else:
        yield value


def check_option_values(params, values: dict, ctx=None) -> None:
    """Refuse, as :class:`click.BadParameter` naming the option, values a method cannot use
    whatever type its options declared: a NaN or infinite float (``click.FLOAT`` and
    ``FloatRange`` let them through), and a seed (an option whose name is ``seed``) outside
    0 .. 2**64 - 1. ``params``: the click parameters; ``values``: name -> parsed value."""
    for p in params:
        value = values.get(p.name)
        if value is None:
            continue
        for v in _values(value):
            if isinstance(v, float) and not math.isfinite(v):
                describe = getattr(p.type, "_describe_range", None)
                rng = describe() if callable(describe) else ""
                raise click.BadParameter(f"{v} is not a finite number; give a finite value"
                                         + (f" in the range {rng}" if rng else ""), ctx=ctx, param=p)
            if p.name == "seed" and isinstance(v, int) and not isinstance(v, bool) and not 0 <= v <= SEED_MAX:
                raise click.BadParameter(f"{v} is not a valid seed: give an integer from 0 to 2**64 - 1",
                                         ctx=ctx, param=p)


# ------------------------------------------------------------------------------ from data to click
def _shown(value) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    return f"{value:g}" if isinstance(value, float) else str(value)


def click_option(opt: Option) -> click.Option:
    """The click option of one :class:`Option` record (unset: ``None``, so the method's own
    default applies)."""
    help_ = opt.help + (f" [default: {opt.default}]" if opt.default not in (None, "") else "")
    decls = [opt.flag, opt.name]
    if opt.kind == "flag":
        return click.Option(decls, is_flag=True, default=None, help=help_)
    if opt.kind == "switch":
        return click.Option([f"{opt.flag}/--no-{opt.flag[2:]}", opt.name], default=None, help=help_)
    kinds = {
        "seed": Seed,
        "str": lambda: click.STRING,
        "choice": lambda: click.Choice(list(opt.choices)),
        "int": lambda: click.IntRange(min=opt.min, max=opt.max, min_open=opt.min_open, max_open=opt.max_open),
        "float": lambda: FiniteFloat(opt.min, opt.max, min_open=opt.min_open, max_open=opt.max_open),
    }
    return click.Option(decls, type=kinds[opt.kind](), default=None, help=help_)


def config_options(config) -> list:
    """:class:`Option` records of the fields of a settings dataclass that name a command-line
    ``flag`` in their metadata, in the order of ``config.CLI`` (the fields a method exposes)."""
    by_name = {f.name: f for f in dataclasses.fields(config)}
    out = []
    for name in config.CLI:
        f = by_name[name]
        meta = f.metadata
        base = str(f.type).split("|")[0].strip()
        choices = tuple(config.CHOICES.get(name, ()))
        if name == "seed":
            kind = "seed"
        elif base == "bool":
            kind = "switch"
        elif choices:
            kind = "choice"
        else:
            kind = base
        low = meta.get("min", config.AT_LEAST.get(name, 0)) if kind in ("int", "float") else None
        out.append(Option(meta["flag"], name, kind, help=meta.get("help", ""), default=_shown(f.default),
                          choices=choices, min=low, min_open=name in config.POSITIVE,
                          max=meta.get("max"), max_open=meta.get("max_open", False)))
    return out


def method_params(method: Method) -> list:
    """The click options of a method: its settings dataclass's exposed fields, then its other
    options (:class:`Option` records, or click parameters a plugin built itself)."""
    opts = config_options(method.config_class()) if method.config is not None else []
    opts += method.option_list()
    return [click_option(o) if isinstance(o, Option) else o for o in opts]


def distance_options(dso_help: str, dsd_help: str):
    """``--DSO`` and ``--DSD`` (mm, positive, or absent) with each command's own help."""
    def decorate(f):
        f = click.option("--DSD", "DSD", type=FiniteFloat(min=0, min_open=True), default=None, help=dsd_help)(f)
        return click.option("--DSO", "DSO", type=FiniteFloat(min=0, min_open=True), default=None, help=dso_help)(f)
    return decorate


def mesh_space_option(what: str):
    """``--mesh-space RAS|LPS``: the coordinate frame of the ``what`` surface files that declare none
    (no SPACE= tag); unset, such a file is read as LPS (3D Slicer's reading) with a warning."""
    return click.option("--mesh-space", type=click.Choice(["RAS", "LPS"], case_sensitive=False), default=None,
                        callback=lambda ctx, param, value: value.upper() if value else None,
                        help=f"frame of {what} surface files without a SPACE= tag [default: LPS, as 3D Slicer "
                             "reads them, with a warning]; a tagged file is read in its own frame")


# ------------------------------------------------------------------------ the command-line convention
# One name per meaning across every command (docs/commands.md, "Conventions"; tests/test_cli_convention.py):
#   -o/--out       where the command writes its result
#   --set K=V      a method's settings (simulate: the simulation's settings), parsed by clgs.methods.settings
#   --views N      always a count of views; a choice of views is --angles / --view-sets
#   --force        overwrite existing outputs (FORCE_HELP starts its help everywhere)
#   --noise/--no-noise, --progress/--no-progress: a switch always has both forms
FORCE_HELP = "overwrite existing outputs"


class AliasOption(click.Option):
    """An option that also answers to older names (``aliases``), left out of ``--help``."""

    def __init__(self, param_decls, aliases=(), **kwargs):
        self.aliases = tuple(a.strip(" /") for a in aliases)
        super().__init__(list(param_decls) + list(aliases), **kwargs)

    def get_help_record(self, ctx):
        opts, secondary = self.opts, self.secondary_opts
        self.opts = [o for o in opts if o not in self.aliases]
        self.secondary_opts = [o for o in secondary if o not in self.aliases]
        try:
            return super().get_help_record(ctx)
        finally:
            self.opts, self.secondary_opts = opts, secondary


def out_option(help: str, name: str = "out", aliases=(), **kwargs):
    """``-o/--out``: where the command writes (``name``: the callback's parameter)."""
    kwargs.setdefault("default", None)
    return click.option("--out", "-o", name, cls=AliasOption, aliases=aliases, help=help, **kwargs)


def force_option(detail: str = "", aliases=()):
    """``--force``: overwrite existing outputs, the one meaning of the flag (``detail``: what that is here)."""
    return click.option("--force", "force", cls=AliasOption, aliases=aliases, is_flag=True,
                        help=FORCE_HELP + (f": {detail}" if detail else ""))

