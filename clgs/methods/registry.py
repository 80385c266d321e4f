"""The registry of reconstruction methods and how they are found: :class:`Method` and
:class:`Option` records, :func:`register` / :func:`register_lazy`, and a pluggy plugin manager over
the entry-point group ``clgs.methods``, whose plugins implement ``register_methods(register)``
(:mod:`clgs.anatomy.hookspecs`); the built-in methods (:mod:`.builtin`) come through the same
manager. A plugin that fails to import, or whose hook raises or registers something else than a
:class:`Method`, is a :class:`clgs.anatomy.plugins.PluginWarning` naming its package; two
providers of one method name are a :class:`MethodError` naming both. :mod:`clgs.methods`
describes the records."""
from __future__ import annotations

import importlib
import importlib.metadata
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import pluggy

from clgs.anatomy import hookspecs
from clgs.anatomy.plugins import PluginWarning
from clgs.errors import ClgsError

__all__ = ["Method", "Option", "register", "register_lazy", "get", "names", "describe", "MethodError", "GROUP",
           "Registrar", "MethodPlugins", "manager"]


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
    default: str | None = None
    choices: tuple = ()
    min: float | None = None
    max: float | None = None
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
    run: Callable | str
    options: list | str | Callable = field(default_factory=list)
    help: str = ""
    # True: the output folder is built in a temporary sibling and renamed when done (nothing
    # half-written). False: the method manages its folder itself (e.g. checkpoints it can resume).
    atomic_dir: bool = True

    # a settings dataclass (or "module:attr") whose fields named in its ``CLI`` are options too
    config: type | str | None = None

    def callable(self) -> Callable:
        return _resolve(self.run)

    def config_class(self) -> type | None:
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
    """Register the methods installed plugins provide (once per process): the entry-point group
    ``clgs.methods`` (:class:`MethodPlugins`), then the deprecated ``clgs_methods()`` of anatomy plugins. A
    bad record is a warning naming its package; a name clash with another method is an error
    naming both."""
    if _PLUGINS_SEEN[0]:
        return
    _PLUGINS_SEEN[0] = True
    load_entry_points()
    load_deprecated_anatomy_methods()


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



GROUP = "clgs.methods"

#: method name -> the package that registered it (for clash messages)
PROVIDERS: dict = {}


class Registrar:
    """The ``register`` a plugin's ``register_methods`` receives: ``register(method)`` and
    ``register.lazy(name, module, help="")`` (the module registers the method, or defines
    ``METHOD``, when it is first used)."""

    def __init__(self, package: str):
        self.package = package

    def _check_free(self, name: str) -> None:
        if name in _REGISTRY or name in _LAZY:
            other = PROVIDERS.get(name, "clgs")
            raise MethodError(
                f"two providers of the reconstruction method {name!r}: package {other!r} and plugin package "
                f"{self.package!r}; uninstall one of them or rename its method")

    def __call__(self, method) -> None:
        if not isinstance(method, Method):
            raise TypeError(f"register() takes clgs.methods.Method records, got {type(method).__name__}")
        self._check_free(method.name)
        register(method)
        PROVIDERS[method.name] = self.package

    def lazy(self, name: str, module: str, help: str = "") -> None:
        if not isinstance(name, str) or not isinstance(module, str):
            raise TypeError(f"register.lazy(name, module) takes two strings, got {name!r}, {module!r}")
        self._check_free(name)
        register_lazy(name, module, help=help)
        PROVIDERS[name] = self.package


class MethodPlugins:
    """The plugin manager of method plugins."""

    def __init__(self):
        self.pm = pluggy.PluginManager(hookspecs.PROJECT)
        self.pm.add_hookspecs(hookspecs)
        self.failures = []  # (plugin name, package, reason)

    def _warn(self, name, package, reason):
        self.failures.append((name, package, reason))
        warnings.warn(f"clgs: skipping method plugin {name!r} from package {package!r}: {reason}", PluginWarning,
                      stacklevel=4)

    def register_plugin(self, plugin, name: str | None = None, package: str = "") -> None:
        """Register ``plugin`` (a module or object implementing ``register_methods``) and register
        its methods now. A hook that raises is a warning; a name clash is a MethodError."""
        registered = self.pm.register(plugin, name=name)
        package = package or registered or ""
        for impl in self.pm.hook.register_methods.get_hookimpls():
            if impl.plugin is not plugin:
                continue
            try:
                impl.function(Registrar(package))
            except MethodError:
                raise
            except Exception as exc:  # noqa: BLE001 - a broken plugin must not break clgs
                self._warn(registered, package, f"register_methods() raised {type(exc).__name__}: {exc}")

    def load_entry_points(self, group: str = GROUP) -> None:
        """Import and register every entry point of ``group`` (a failed import is a warning)."""
        for ep in sorted(importlib.metadata.entry_points(group=group), key=lambda e: e.name):
            dist = getattr(ep, "dist", None)
            package = dist.name if dist is not None else ep.value.split(":")[0]
            if self.pm.get_plugin(ep.name) is not None:
                self._warn(ep.name, package, f"another method plugin is already registered under the name {ep.name!r}")
                continue
            try:
                plugin = ep.load()
            except Exception as exc:  # noqa: BLE001 - any failure of a third-party import is reported
                self._warn(ep.name, package, f"{type(exc).__name__}: {exc}")
                continue
            self.register_plugin(plugin, name=ep.name, package=package)


_MANAGER: list = []


def manager() -> MethodPlugins:
    """The process's method plugin manager."""
    if not _MANAGER:
        _MANAGER.append(MethodPlugins())
    return _MANAGER[0]


def load_entry_points() -> None:
    manager().load_entry_points()


def load_deprecated_anatomy_methods() -> None:
    """Methods from ``clgs_methods()`` of plugins in the group ``clgs.anatomies`` (deprecated)."""
    from clgs.anatomy import plugins as anatomy_plugins

    for package, m in anatomy_plugins.registry().methods():
        if not isinstance(m, Method):
            warnings.warn(f"plugin package {package!r}: clgs_methods() must return clgs.methods.Method records, "
                          f"got {type(m).__name__}; ignored", PluginWarning, stacklevel=3)
            continue
        warnings.warn(f"plugin package {package!r}: the hook clgs_methods() in the group 'clgs.anatomies' is "
                      f"deprecated; implement register_methods(register) in the group {GROUP!r} "
                      "(docs/plugins.md)", DeprecationWarning, stacklevel=3)
        Registrar(package)(m)
