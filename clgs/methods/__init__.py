"""Reconstruction methods that ``clgs reconstruct --method NAME`` can run.

A :class:`Method` has a ``name``, a ``run`` callable ``run(scan, out_dir, **options) -> dict``
(the dict holds at least ``"volume"``: (Z, Y, X) float32 in the scan's units, 1/mm; optionally
``"files"`` it wrote and ``"info"`` figures for the report), its ``options`` (:class:`Option`
records, or click parameters) and, for a method with a settings dataclass, its ``config`` (the
fields listed in its ``CLI`` are options too), and a one-line ``help``. ``out_dir`` is a folder
the method may fill with extra outputs, or None when the user asked for a single volume file.
Options left unset on the command line are not passed, so the callable's own defaults apply;
one exception: a resumed run (``--resume`` given) of a method with an ``iterations`` option gets
``iterations=None`` when ``--iterations`` is not given, meaning "the iterations the interrupted
run was started with", never a new-run default.

Registering a method (e.g. from a plugin or another clgs module)::

    from clgs.methods import Method, register
    register(Method("mine", run="mypkg.recon:run", options="mypkg.recon:OPTIONS", help="..."))

``run`` and ``options`` may be given as ``"module:attr"`` strings; they are imported only when that
method is chosen, so listing methods stays fast. A method known only by name can be registered
lazily with :func:`register_lazy` (``module`` is imported on first use and must register it, or
expose it as ``METHOD``); R2-Gaussian (``r2gs``) is declared that way, from :mod:`clgs.methods.r2gs`.
Installed plugins provide methods the way they provide anatomies, through one mechanism: a pluggy
hook, ``clgs_methods()`` returning :class:`Method` records, in a package registered in the
entry-point group ``clgs.anatomies`` (see :mod:`clgs.anatomy.hookspecs`).

One module per built-in method (:mod:`.fdk`, :mod:`.sart`, :mod:`.r2gs`, :mod:`.shape_guided`),
each thin: the work is in :mod:`clgs.ct` and :mod:`clgs.fit`. The command line makes the click
options (:mod:`clgs.cli.options`); this package imports neither click nor anything heavy.

May import: :mod:`clgs.fit`, :mod:`clgs.shape`, :mod:`clgs.anatomy`, :mod:`clgs.ct` and every
layer below them. Not the experiment or the CLI.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable, Optional, Union

from clgs.errors import ClgsError
from clgs.limits import MAX_ITERATIONS

__all__ = ["Method", "Option", "register", "register_lazy", "get", "names", "describe", "MethodError"]


@dataclass(frozen=True)
class Option:
    """One command-line option of a method, as data (:mod:`clgs.cli.options` makes the click
    option). ``flag``: ``--name``; ``name``: the keyword of the method's ``run``; ``kind``: ``int``,
    ``float`` (finite), ``choice``, ``flag`` (on when given), ``switch`` (``--x/--no-x``), ``seed``
    or ``str``; ``default``: what the help shows as the default (the method's own applies when the
    option is not given); ``min``/``max`` (``*_open``: excluded) bound numbers."""

    flag: str
    name: str
    kind: str = "float"
    help: str = ""
    default: Optional[str] = None
    choices: tuple = ()
    min: Optional[float] = None
    max: Optional[float] = None
    min_open: bool = False
    max_open: bool = False


class MethodError(ClgsError, LookupError):
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

    # a settings dataclass (or "module:attr") whose fields named in its ``CLI`` are options too
    config: Union[type, str, None] = None

    def callable(self) -> Callable:
        return _resolve(self.run)

    def config_class(self) -> Optional[type]:
        return None if self.config is None else _resolve(self.config)

    def option_list(self) -> list:
        """The method's own options: :class:`Option` records (or click parameters)."""
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


_PLUGINS_SEEN = [False]


def _register_plugin_methods() -> None:
    """Register the methods installed plugins provide (once per process; a bad record is a warning
    naming its package, and a name clash with another method is an error naming both)."""
    if _PLUGINS_SEEN[0]:
        return
    _PLUGINS_SEEN[0] = True
    import warnings

    from clgs.anatomy import plugins

    for package, m in plugins.registry().methods():
        if not isinstance(m, Method):
            warnings.warn(f"plugin package {package!r}: clgs_methods() must return clgs.methods.Method records, "
                          f"got {type(m).__name__}; ignored", stacklevel=2)
            continue
        if m.name in _REGISTRY or m.name in _LAZY:
            raise MethodError(f"two providers of the reconstruction method {m.name!r}: clgs and plugin package "
                              f"{package!r}; uninstall one of them or rename its method")
        register(m)


def names() -> list:
    """Every method name available (without importing any method's module)."""
    _register_plugin_methods()
    return sorted(set(_REGISTRY) | set(_LAZY))


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
    _register_plugin_methods()
    if name in _REGISTRY:
        return _REGISTRY[name]
    raise MethodError(f"unknown reconstruction method {name!r}; available: {', '.join(names())}")


# ------------------------------------------------------------------------------ built-ins
_FILTERS = ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")  # clgs.ct.fdk.FILTERS, without importing it

register(Method(
    "fdk", "clgs.methods.fdk:run", help="FDK filtered backprojection (fast, streaky at few views)",
    options=[
        Option("--filter", "filter", "choice", "FDK ramp filter window", default="ram-lak", choices=_FILTERS),
        Option("--short-scan", "short_scan", "choice",
               "redundancy (Parker-like) weights for arcs short of a full circle", default="auto",
               choices=("auto", "on", "off")),
    ],
))
register(Method(
    "sart", "clgs.methods.sart:run", help="SART / OS-SART iterative reconstruction (non-negative)",
    options=[
        Option("--iterations", "iterations", "int", "number of SART iterations (full passes over the views)",
               min=1, max=MAX_ITERATIONS),
        Option("--subsets", "subsets", "int", "ordered subsets per iteration (1 = SART, more = OS-SART)", min=1,
               max=MAX_ITERATIONS),
        Option("--relaxation", "relaxation", "float", "relaxation factor of each update, in (0, 2)", min=0, max=2,
               min_open=True, max_open=True),
    ],
))
register_lazy("r2gs", "clgs.methods.r2gs", help="R2-Gaussian: radiative Gaussian splatting (slow, best at few views)")
register_lazy("shape", "clgs.methods.shape_guided",
              help="shape-guided Gaussian splatting with an anatomy's shape model and density atlas")
