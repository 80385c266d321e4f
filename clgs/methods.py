"""Reconstruction methods that ``clgs reconstruct --method NAME`` can run.

A :class:`Method` has a ``name``, a ``run`` callable ``run(scan, out_dir, **options) -> dict``
(the dict holds at least ``"volume"``: (Z, Y, X) float32 in the scan's units, 1/mm; optionally
``"files"`` it wrote and ``"info"`` figures for the report), its click ``options`` and a one-line
``help``. ``out_dir`` is a folder the method may fill with extra outputs, or None when the user
asked for a single volume file. Options left unset on the command line are not passed, so the
callable's own defaults apply.

Registering a method (e.g. from a plugin or another clgs module)::

    from clgs.methods import Method, register
    register(Method("mine", run="mypkg.recon:run", options="mypkg.recon:OPTIONS", help="..."))

``run`` and ``options`` may be given as ``"module:attr"`` strings; they are imported only when that
method is chosen, so listing methods stays fast. A method known only by name can be registered
lazily with :func:`register_lazy` (``module`` is imported on first use and must register it, or
expose it as ``METHOD``); R2-Gaussian (``r2gs``) is declared that way, from :mod:`clgs.r2gs`.
Installed distributions may also declare methods in the entry-point group ``clgs.methods``
(name -> a :class:`Method` object or a module that registers it).

This module imports only click and the standard library.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable, Union

import click

__all__ = ["Method", "register", "register_lazy", "get", "names", "describe", "MethodError"]


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
def run_fdk(scan, out_dir=None, filter: str = "ram-lak", short_scan="auto") -> dict:
    """Feldkamp-Davis-Kress (FBP for parallel beam), with redundancy weights for short arcs."""
    from clgs.ct.fdk import fdk

    short_scan = {"on": True, "off": False}.get(short_scan, short_scan)
    return {"volume": fdk(scan.projections, scan.geometry, filter=filter, short_scan=short_scan)}


def run_sart(scan, out_dir=None, iterations=None, subsets=None, relaxation=None, progress: bool = True) -> dict:
    """SART (``subsets`` = 1) or OS-SART (``subsets`` > 1), non-negative; unset options keep
    :func:`clgs.ct.sart.sart`'s defaults."""
    from clgs.ct.sart import sart

    kwargs = {k: v for k, v in (("n_iter", iterations), ("subsets", subsets), ("relaxation", relaxation))
              if v is not None}
    return {"volume": sart(scan.projections, scan.geometry, verbose=progress, **kwargs)}


_FILTERS = ["ram-lak", "shepp-logan", "cosine", "hamming", "hann"]

register(Method(
    "fdk", run_fdk, help="FDK filtered backprojection (fast, streaky at few views)",
    options=[
        click.Option(["--filter", "filter"], type=click.Choice(_FILTERS), default=None,
                     help="FDK ramp filter window [default: ram-lak]"),
        click.Option(["--short-scan", "short_scan"], type=click.Choice(["auto", "on", "off"]), default=None,
                     help="redundancy (Parker-like) weights for arcs short of a full circle [default: auto]"),
    ],
))
register(Method(
    "sart", run_sart, help="SART / OS-SART iterative reconstruction (non-negative)",
    options=[
        click.Option(["--iterations", "iterations"], type=click.IntRange(min=1), default=None,
                     help="number of SART iterations (full passes over the views)"),
        click.Option(["--subsets", "subsets"], type=click.IntRange(min=1), default=None,
                     help="ordered subsets per iteration (1 = SART, more = OS-SART)"),
        click.Option(["--relaxation", "relaxation"], type=click.FloatRange(0, 2, min_open=True, max_open=True),
                     default=None, help="relaxation factor of each update, in (0, 2)"),
    ],
))
register_lazy("r2gs", "clgs.r2gs", help="R2-Gaussian: radiative Gaussian splatting (slow, best at few views)")
register_lazy("shape", "clgs.shape_guided",
              help="shape-guided Gaussian splatting with an anatomy's shape model and density atlas")
