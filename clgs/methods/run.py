"""One way to run a registered method: :func:`run_method`, used by ``clgs reconstruct``,
``clgs <anatomy> reconstruct``, ``clgs batch`` and Python alike, so that every one of them
answers "does method M take setting K?" the same way (:func:`accepted_settings`) and refuses an
unknown key with the same words (:func:`check_method_settings`).

A method's settings are its callable's keyword parameters (not ``scan``, ``out_dir``, ``anatomy``),
the fields of its config dataclass when the callable passes ``**settings`` on to it, a few
keywords such a callable names beside its config, and its registered options. A callable taking
``**kwargs`` without a config is open: any key is passed on.
"""
from __future__ import annotations

import dataclasses
import inspect
import typing

from clgs.methods.registry import MethodError, get

__all__ = ["run_method", "accepted_settings", "check_method_settings", "method_accepts", "UnknownSettingError"]

_EXTRA_KEYWORDS = {  # method -> keyword arguments its run passes on beside its config's fields
    "shape": {"level": float | None},
}
NOT_SETTINGS = {"scan", "out_dir", "out", "anatomy"}  # given by the caller itself, not a setting


class UnknownSettingError(MethodError):
    """A setting the method does not take; the message names the valid keys."""


def _type_hints(obj) -> dict:
    try:
        return typing.get_type_hints(obj)
    except Exception:  # noqa: BLE001 - unresolvable annotations: no type check for them
        return {}


def _method(method):
    return get(method) if isinstance(method, str) else method


def _signature_settings(m) -> tuple:
    """(key -> type hint or None from the callable's parameters, whether it takes ``**kwargs``)."""
    run = m.callable()
    hints, takes_kwargs = {}, False
    run_hints = _type_hints(run)
    for i, (k, p) in enumerate(inspect.signature(run).parameters.items()):
        if p.kind == p.VAR_KEYWORD:
            takes_kwargs = True
        elif p.kind != p.VAR_POSITIONAL and i > 0 and k not in NOT_SETTINGS:
            hints[k] = run_hints.get(k)
    return hints, takes_kwargs


def settings_spec(method) -> tuple:
    """(key -> type hint or None, open, config dataclass or None) of a method (name or record)."""
    m = _method(method)
    hints, takes_kwargs = _signature_settings(m)
    cls = None
    if m.config is not None and takes_kwargs:
        cls = m.config_class()
        cls_hints = _type_hints(cls)
        for f in dataclasses.fields(cls):
            hints.setdefault(f.name, cls_hints.get(f.name))
        for k, h in _EXTRA_KEYWORDS.get(m.name, {}).items():
            hints.setdefault(k, h)
    try:
        for o in m.option_list():
            name = getattr(o, "name", None)
            if name and name not in NOT_SETTINGS:
                hints.setdefault(name, None)
    except Exception:  # noqa: BLE001 - a method without usable options: its parameters still count
        pass
    return hints, takes_kwargs and cls is None, cls


def accepted_settings(method) -> dict:
    """The settings a method takes: key -> type hint (None when it names none). ``method`` is a
    name or a :class:`clgs.methods.Method`."""
    return settings_spec(method)[0]


def method_accepts(method, key: str) -> bool:
    """Whether the method takes the setting ``key`` (always, for an open method)."""
    hints, open_, _ = settings_spec(method)
    return open_ or key in hints


def check_surface_closing(method, surface_closing) -> None:
    """A closing given (``surface_closing`` not None) must reach the surface written: a
    :class:`MethodError` for a method that writes its own bone surface (its callable names
    ``surface_level``) but takes no ``surface_closing``. The one rule :func:`run_method` and the
    commands (before they claim their outputs) apply."""
    if surface_closing is None:
        return
    m = _method(method)
    params = inspect.signature(m.callable()).parameters
    if "surface_level" in params and "surface_closing" not in params:
        raise MethodError(f"the {m.name} method writes its own bone surface and takes no surface closing: "
                          "leave surface_closing (--surface-closing) out")


def unknown_setting_message(key: str, owner: str, valid) -> str:
    """The one wording of an unknown setting, everywhere."""
    return f"unknown setting {key!r} for {owner}; valid keys: {', '.join(sorted(valid))}"


def check_method_settings(method, settings: dict | None) -> dict:
    """``settings`` unchanged when the method takes every key; else :class:`UnknownSettingError`
    naming the valid keys (the first unknown key, in the order given)."""
    m = _method(method)
    hints, open_, _ = settings_spec(m)
    for key in settings or {}:
        if key not in hints and not open_:
            raise UnknownSettingError(unknown_setting_message(key, f"the {m.name} method", hints))
    return dict(settings or {})


def run_method(name, scan, out_dir=None, settings: dict | None = None, *, anatomy=None, seed=None,
               resume: bool = False, progress: bool | None = None, surface_level=None,
               surface_closing=None) -> dict:
    """Run the registered method ``name`` on ``scan`` (a :class:`clgs.Scan`) and return its
    result dict (at least ``"volume"``, (Z, Y, X) float32 in 1/mm).

    ``out_dir``: a folder for the method's extra outputs (checkpoints, logs), or None.
    ``settings``: the method's settings by name (checked: an unknown key is an
    :class:`UnknownSettingError` naming the valid ones). ``anatomy`` goes to a method whose callable
    names an ``anatomy`` parameter, ``seed`` and ``progress`` (when not None) to one that takes them,
    ``surface_level`` and ``surface_closing`` (when not None) to one that writes its own bone surface
    and names them (a method that writes its own but takes no ``surface_closing`` is a
    :class:`MethodError`: its surface would not be the one asked for). ``resume=True``
    continues the run in ``out_dir`` from its checkpoint; without an ``iterations`` setting it goes
    on to the iterations the run was started with (``iterations=None``), never a new-run default.
    """
    m = _method(name)
    run = m.callable()
    kwargs = check_method_settings(m, settings)
    params = inspect.signature(run).parameters
    if resume:
        if not method_accepts(m, "resume"):
            raise MethodError(f"the {m.name} method cannot resume a run (it keeps no checkpoint)")
        kwargs["resume"] = True
        if "iterations" not in kwargs and method_accepts(m, "iterations"):
            kwargs["iterations"] = None
    if seed is not None and method_accepts(m, "seed"):
        kwargs["seed"] = int(seed)
    if progress is not None and method_accepts(m, "progress"):
        kwargs.setdefault("progress", progress)
    if "anatomy" in params:
        kwargs["anatomy"] = anatomy
    if surface_level is not None and "surface_level" in params:
        kwargs["surface_level"] = surface_level
    check_surface_closing(m, surface_closing)
    if surface_closing is not None and "surface_level" in params:
        kwargs["surface_closing"] = surface_closing
    return run(scan, out_dir, **kwargs)
