"""Anatomy plugins: discovery through entry points, a registry of :class:`Anatomy` objects and
of the click commands plugins add.

A plugin is any distribution that declares an entry point in the group ``clgs.anatomies``
whose object (usually a module) implements the hook ``clgs_anatomies()`` and/or
``register_commands(cli)`` / ``register_anatomy_commands(anatomy, group)`` (see
:mod:`clgs.anatomy.hookspecs`). Built-in anatomies are registered the same way. (Methods have
their own group, ``clgs.methods``: :mod:`clgs.methods`.)

* Discovery is cheap: reading entry-point metadata and importing the plugin modules; no
  model data is loaded and torch / pyopencl are not imported (plugins must keep their module
  import light too).
* Each Anatomy records the distribution that provided it (``Anatomy.package``); a missing
  version is filled from the distribution's version.
* Two plugins providing the same anatomy name: :class:`DuplicateAnatomyError` naming both
  distributions.
* A plugin that cannot be imported, or whose hook raises or returns something else than
  Anatomy objects: a :class:`PluginWarning` with the reason; the other plugins keep working.
"""
from __future__ import annotations

import importlib.metadata
import warnings

import pluggy

from clgs.anatomy import hookspecs
from clgs.anatomy.record import Anatomy
from clgs.commands import BUILTIN_COMMANDS
from clgs.errors import ClgsError

GROUP = "clgs.anatomies"


class PluginWarning(UserWarning):
    """An anatomy plugin could not be used (it is skipped)."""


class PluginError(ClgsError):
    """A plugin problem that must stop the command (shown as a one-line error by the CLI)."""


class DuplicateAnatomyError(PluginError):
    """Two plugins provide an anatomy with the same name."""


class UnknownAnatomyError(PluginError, LookupError):
    """No installed plugin provides the requested anatomy."""


class Registry:
    """A pluggy plugin manager plus the anatomies its plugins provide, by name."""

    def __init__(self):
        self.pm = pluggy.PluginManager(hookspecs.PROJECT)
        self.pm.add_hookspecs(hookspecs)
        self._package = {}  # plugin name -> (distribution name, version)
        self._anatomies: dict | None = None
        self.failures = []  # (plugin name, package, reason)
        self._commands_added = set()  # ids of the root groups already given the plugins' commands

    # ---- registration
    def register(self, plugin, name: str | None = None, package: str = "", version: str = "") -> None:
        """Register a plugin object (module or instance with ``clgs_anatomies``) from ``package``."""
        name = self.pm.register(plugin, name=name)
        self._package[name] = (package or name, version)
        self._anatomies = None

    def _warn(self, name, package, reason):
        self.failures.append((name, package, reason))
        warnings.warn(f"clgs: skipping anatomy plugin {name!r} from package {package!r}: {reason}",
                      PluginWarning, stacklevel=3)

    def load_entry_points(self, group: str = GROUP) -> None:
        """Import every entry point of ``group``; failures become warnings."""
        for ep in sorted(importlib.metadata.entry_points(group=group), key=lambda e: e.name):
            dist = getattr(ep, "dist", None)
            package = dist.name if dist is not None else ep.value.split(":")[0]
            version = dist.version if dist is not None else ""
            if self.pm.get_plugin(ep.name) is not None or self.pm.is_blocked(ep.name):
                if self._package.get(ep.name, (None,))[0] == package:
                    continue
                self._warn(ep.name, package, f"another plugin is already registered under the entry-point "
                                             f"name {ep.name!r} (from {self._package.get(ep.name, ('?',))[0]!r})")
                continue
            try:
                plugin = ep.load()
                self.register(plugin, name=ep.name, package=package, version=version)
            except Exception as exc:  # noqa: BLE001 - any failure of a third-party import is reported
                self._warn(ep.name, package, f"{type(exc).__name__}: {exc}")

    # ---- queries
    def _results(self, hook: str):
        """(hookimpl, package, version, result) of each plugin's ``hook``; a plugin whose hook
        raises is a warning naming its package, and is left out."""
        for impl in getattr(self.pm.hook, hook).get_hookimpls():
            package, version = self._package.get(impl.plugin_name, (impl.plugin_name, ""))
            try:
                result = impl.function()
            except Exception as exc:  # noqa: BLE001 - a broken plugin must not break clgs
                self._warn(impl.plugin_name, package, f"{hook}() raised {type(exc).__name__}: {exc}")
                continue
            yield impl, package, version, result

    def anatomies(self) -> dict:
        """name -> Anatomy from every registered plugin (cached)."""
        if self._anatomies is not None:
            return self._anatomies
        found = {}
        for impl, package, version, returned in self._results("clgs_anatomies"):
            result = [returned] if isinstance(returned, Anatomy) else returned
            if not isinstance(result, (list, tuple)) or not all(isinstance(a, Anatomy) for a in result):
                self._warn(impl.plugin_name, package, "clgs_anatomies() must return a list of clgs.anatomy.Anatomy, "
                                                      f"got {type(result).__name__}")
                continue
            for a in result:
                bad = _check_name(a.name)
                if bad:
                    self._warn(impl.plugin_name, package, bad)
                    continue
                a.package = package
                if (not a.version or a.version == "0") and version:
                    a.version = version
                if a.name in found:
                    other = found[a.name]
                    raise DuplicateAnatomyError(
                        f"two plugins provide the anatomy {a.name!r}: package {other.package!r} and package "
                        f"{a.package!r}. Uninstall one of them (pip uninstall {a.package}) or rename its anatomy.")
                found[a.name] = a
        self._anatomies = dict(sorted(found.items()))
        return self._anatomies

    def names(self) -> list:
        return list(self.anatomies())

    # ---- commands
    def _add_from_hook(self, hook: str, target, taken, where: str, **kwargs) -> None:
        """Call each plugin's ``hook`` (with those of ``kwargs`` it takes); a command it adds under a
        name in ``taken`` (or one replacing a command already there) is removed with a warning, and so
        is everything a plugin adds before its hook raises. ``target``: the click group added to."""
        group = target
        for impl in getattr(self.pm.hook, hook).get_hookimpls():
            package = self._package.get(impl.plugin_name, (impl.plugin_name, ""))[0]
            before = dict(group.commands)
            try:
                impl.function(*[kwargs[a] for a in impl.argnames])
            except Exception as exc:  # noqa: BLE001 - a broken plugin must not break clgs
                group.commands.clear()
                group.commands.update(before)
                self._warn(impl.plugin_name, package, f"{hook}() raised {type(exc).__name__}: {exc}")
                continue
            for name, cmd in list(group.commands.items()):
                if before.get(name) is cmd:
                    continue
                if name in before or name in taken:
                    self._warn(impl.plugin_name, package, f"command {name!r} clashes with the command "
                                                          f"'{where} {name}'; left out")
                    if name in before:
                        group.commands[name] = before[name]
                    else:
                        del group.commands[name]

    def add_commands(self, cli) -> None:
        """Give the root click group ``cli`` the commands plugins add with ``register_commands(cli)``
        (once per group; names of built-in commands and anatomies are refused)."""
        if id(cli) in self._commands_added:
            return
        self._commands_added.add(id(cli))
        self._add_from_hook("register_commands", cli, _RESERVED | set(self.names()), "clgs", cli=cli)

    def add_anatomy_commands(self, anatomy: Anatomy, group) -> None:
        """Give ``clgs <anatomy.name>`` (``group``) the commands plugins add with
        ``register_anatomy_commands(anatomy, group)`` (the generic commands' names are refused)."""
        self._add_from_hook("register_anatomy_commands", group, set(group.commands), f"clgs {anatomy.name}",
                            anatomy=anatomy, group=group)

    def methods(self) -> list:
        """Deprecated path: (plugin's package, object) for every reconstruction method a plugin of
        this group provides through ``clgs_methods()`` (methods have their own entry-point group,
        ``clgs.methods``, now); :mod:`clgs.methods` checks and registers them. A plugin whose hook
        fails is a warning, not a crash."""
        found = []
        for _, package, _, result in self._results("clgs_methods"):
            found.extend((package, m) for m in (result if isinstance(result, (list, tuple)) else [result]))
        return found

    def get(self, name: str) -> Anatomy:
        found = self.anatomies()
        if name not in found:
            have = ", ".join(found) or "none installed"
            raise UnknownAnatomyError(f"no anatomy named {name!r} (available: {have}); install its plugin "
                                      f"package (entry-point group {GROUP!r})")
        return found[name]


_RESERVED = frozenset(BUILTIN_COMMANDS)  # `clgs NAME` runs the built-in command, never the anatomy


def _check_name(name) -> str:
    if not isinstance(name, str) or not name or name != name.lower() or not all(c.isalnum() or c in "-_" for c in name):
        return f"anatomy name {name!r} must be a non-empty lower-case word (letters, digits, '-', '_')"
    if name in _RESERVED:
        return f"anatomy name {name!r} clashes with the built-in command 'clgs {name}'"
    return ""


_default: Registry | None = None


def registry(reload: bool = False) -> Registry:
    """The process-wide registry, loaded from installed entry points on first use."""
    global _default  # noqa: PLW0603 - the process-wide registry, loaded once
    if _default is None or reload:
        reg = Registry()
        reg.load_entry_points()
        _default = reg
    return _default


def anatomies() -> dict:
    """name -> Anatomy of every installed plugin."""
    return registry().anatomies()


def anatomy_names() -> list:
    """Names of the installed anatomies, sorted (cheap: metadata and plugin imports only)."""
    return registry().names()


def get_anatomy(name: str) -> Anatomy:
    """The installed anatomy called ``name`` (:class:`UnknownAnatomyError` names the ones there are)."""
    return registry().get(name)
