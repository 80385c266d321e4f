"""Reconstruction methods that ``clgs reconstruct --method NAME`` can run.

A :class:`Method` has a ``name``, a ``run`` callable ``run(scan, out_dir, **options) -> dict``
(the dict holds at least ``"volume"``: (Z, Y, X) float32 in the scan's units, 1/mm; optionally
``"files"`` it wrote and ``"info"`` figures for the report), its click ``options`` and a one-line
``help``. ``out_dir`` is a folder the method may fill with extra outputs, or None when the user
asked for a single volume file. Options left unset on the command line are not passed, so the
callable's own defaults apply; one exception: a resumed run (``--resume`` given) of a method with
an ``iterations`` option gets ``iterations=None`` when ``--iterations`` is not given, meaning "the
iterations the interrupted run was started with", never a new-run default.

Registering a method (e.g. from a plugin or another clgs module)::

    from clgs.methods import Method, register
    register(Method("mine", run="mypkg.recon:run", options="mypkg.recon:OPTIONS", help="..."))

``run`` and ``options`` may be given as ``"module:attr"`` strings; they are imported only when that
method is chosen, so listing methods stays fast. A method known only by name can be registered
lazily with :func:`register_lazy` (``module`` is imported on first use and must register it, or
expose it as ``METHOD``); R2-Gaussian (``r2gs``) is declared that way, from :mod:`clgs.methods.r2gs`.
Installed distributions may also declare methods in the entry-point group ``clgs.methods``
(name -> a :class:`Method` object or a module that registers it).

Option types: click's ``float`` and ``FloatRange`` accept ``nan`` and ``inf`` (NaN passes every
range check), which end as a NumPy error deep in a run; :class:`FiniteFloat` refuses them at
parse time, and :class:`Seed` takes random seeds (0 to 2**64 - 1). :func:`check_option_values`
applies the same rules to values parsed by any method's options (whatever type they declared), so
``clgs reconstruct`` refuses a non-finite float or a negative seed before a run starts.

This module imports only click and the standard library.
"""
from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import Callable, Union

import click

__all__ = ["Method", "register", "register_lazy", "get", "names", "describe", "MethodError", "FiniteFloat", "Seed",
           "check_option_values", "SEED_MAX"]

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


class MethodError(LookupError):
    """An unknown method, or one whose module does not provide what it should."""


def _resolve(target):
    if isinstance(target, str):
        module, _, attr = target.partition(":")
        obj = importlib.import_module(module)
        for part in attr.split(".") if attr else []:
            obj = getattr(obj, part)
        return obj
    return target


@dataclass
class Method:
    """One reconstruction method (see the module doc)."""

    name: str
    run: Union[Callable, str]
    options: Union[list, str, Callable] = field(default_factory=list)
    help: str = ""
    # True: the output folder is built in a temporary sibling and renamed when done (nothing
    # half-written). False: the method manages its folder itself (e.g. checkpoints it can resume).
    atomic_dir: bool = True

    def callable(self) -> Callable:
        return _resolve(self.run)

    def click_options(self) -> list:
        opts = _resolve(self.options)
        if callable(opts) and not isinstance(opts, (list, tuple)):
            opts = opts()
        return list(opts)


_REGISTRY: dict = {}
_LAZY: dict = {}  # name -> (module, help)


def register(method: Method, replace: bool = False) -> Method:
    """Add a method; a second method with the same name is an error unless ``replace``."""
    if not isinstance(method, Method):
        raise TypeError(f"expected a clgs.methods.Method, got {type(method).__name__}")
    if method.name in _REGISTRY and not replace and _REGISTRY[method.name] is not method:
        raise MethodError(f"a reconstruction method named {method.name!r} is already registered")
    _REGISTRY[method.name] = method
    _LAZY.pop(method.name, None)
    return method


def register_lazy(name: str, module: str, help: str = "") -> None:
    """Declare ``name`` as provided by ``module`` (imported when the method is first used)."""
    if name not in _REGISTRY:
        _LAZY[name] = (module, help)


def _entry_points():
    from importlib.metadata import entry_points

    try:
        return list(entry_points(group="clgs.methods"))
    except Exception:  # noqa: BLE001 - a broken distribution must not break the CLI
        return []


def names() -> list:
    """Every method name available (without importing any method's module)."""
    found = set(_REGISTRY) | set(_LAZY) | {ep.name for ep in _entry_points()}
    return sorted(found)


def describe() -> dict:
    """name -> one-line help, for listings."""
    out = {}
    for n in names():
        if n in _REGISTRY:
            out[n] = _REGISTRY[n].help
        elif n in _LAZY:
            out[n] = _LAZY[n][1]
        else:
            out[n] = "(from an installed plugin)"
    return out


def get(name: str) -> Method:
    """The method called ``name``, importing its module if it was declared lazily."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in _LAZY:
        module, _ = _LAZY[name]
        mod = importlib.import_module(module)
        if name not in _REGISTRY and isinstance(getattr(mod, "METHOD", None), Method):
            register(mod.METHOD)
        if name not in _REGISTRY:
            raise MethodError(f"{module} was expected to provide the reconstruction method {name!r} "
                              "(register it, or define METHOD = clgs.methods.Method(...))")
        return _REGISTRY[name]
    for ep in _entry_points():
        if ep.name == name:
            obj = ep.load()
            if isinstance(obj, Method):
                register(obj)
            if name in _REGISTRY:
                return _REGISTRY[name]
            raise MethodError(f"entry point {ep.value!r} did not provide the method {name!r}")
    raise MethodError(f"unknown reconstruction method {name!r}; available: {', '.join(names())}")


# ------------------------------------------------------------------------------ built-ins
_FILTERS = ["ram-lak", "shepp-logan", "cosine", "hamming", "hann"]  # clgs.ct.fdk.FILTERS, without importing it

register(Method(
    "fdk", "clgs.methods.fdk:run", help="FDK filtered backprojection (fast, streaky at few views)",
    options=[
        click.Option(["--filter", "filter"], type=click.Choice(_FILTERS), default=None,
                     help="FDK ramp filter window [default: ram-lak]"),
        click.Option(["--short-scan", "short_scan"], type=click.Choice(["auto", "on", "off"]), default=None,
                     help="redundancy (Parker-like) weights for arcs short of a full circle [default: auto]"),
    ],
))
register(Method(
    "sart", "clgs.methods.sart:run", help="SART / OS-SART iterative reconstruction (non-negative)",
    options=[
        click.Option(["--iterations", "iterations"], type=click.IntRange(min=1), default=None,
                     help="number of SART iterations (full passes over the views)"),
        click.Option(["--subsets", "subsets"], type=click.IntRange(min=1), default=None,
                     help="ordered subsets per iteration (1 = SART, more = OS-SART)"),
        click.Option(["--relaxation", "relaxation"], type=FiniteFloat(0, 2, min_open=True, max_open=True),
                     default=None, help="relaxation factor of each update, in (0, 2)"),
    ],
))
register_lazy("r2gs", "clgs.methods.r2gs", help="R2-Gaussian: radiative Gaussian splatting (slow, best at few views)")
register_lazy("shape", "clgs.methods.shape_guided",
              help="shape-guided Gaussian splatting with an anatomy's shape model and density atlas")
