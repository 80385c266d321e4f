"""``--set KEY=VALUE``: a method's settings given by name on ``clgs <anatomy> reconstruct | demo``.

Settings are checked before a run starts: the keys against the method's settings
(:func:`clgs.methods.run.accepted_settings`: its config dataclass's fields for the Gaussian
methods, else its callable's parameters), the values against
the fields' types, the method's options (ranges, choices, :mod:`clgs.cli.options`), the config's
own checks (kinds, ranges: JsonConfig) and, for methods without a config, the ranges below.
"""
from __future__ import annotations

import json

import click

from clgs.cli.options import method_params
from clgs.limits import MAX_ITERATIONS

_RANGES = [  # every method (the configs check their own ranges too); beyond MAX_ITERATIONS is a typo, not a plan
    (("iterations", "subsets"), lambda v: 1 <= v <= MAX_ITERATIONS, f"between 1 and {MAX_ITERATIONS:,}"),
]


def _range_rule(key: str):
    for names, test, words in _RANGES:
        if any(key == n or (n.endswith("_") and key.startswith(n)) for n in names):
            return test, words
    return None


def method_settings(method: str, m, run=None) -> tuple:
    """(key -> type hint or None, key -> click option, open, config dataclass or None): the settings
    ``--set`` may give the method (:func:`clgs.methods.run.settings_spec`, the one answer, plus the
    click options that convert their values); ``open`` when the method takes keywords this cannot
    list (any key is then passed on)."""
    from clgs.methods.run import NOT_SETTINGS, settings_spec

    hints, open_, cls = settings_spec(m)
    try:
        options = {o.name: o for o in method_params(m) if o.name and o.name not in NOT_SETTINGS}
    except Exception:  # noqa: BLE001 - a method without usable options: its parameters still count
        options = {}
    for k in options:
        hints.setdefault(k, None)
    return hints, options, open_, cls


def _accepts(hint, value) -> bool:
    """Whether ``value`` (parsed from JSON) fits the type ``hint`` (True for types not handled)."""
    import types
    import typing

    if hint is None or hint is typing.Any:
        return True
    origin = typing.get_origin(hint)
    if origin is typing.Union or origin is types.UnionType:
        return any(_accepts(h, value) for h in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if hint in (tuple, list) or origin in (tuple, list):
        return isinstance(value, (list, tuple))
    return True


def _describe(hint) -> str:
    import types
    import typing

    origin = typing.get_origin(hint)
    if origin is typing.Union or origin is types.UnionType:
        return " or ".join(_describe(h) for h in typing.get_args(hint))
    names = {type(None): "null", bool: "true/false", int: "an integer", float: "a number", str: "a string",
             tuple: "a list like [a, b]", list: "a list like [a, b]"}
    return names.get(origin or hint, getattr(hint, "__name__", str(hint)))


def check_settings(method: str, m, run, opts: dict, raw: dict | None = None) -> dict:
    """``opts`` checked against the method's settings (see above): returns them, converted where a
    click option says how (e.g. choices); an unknown key or a bad value is a ``--set`` usage error."""
    import dataclasses
    import math

    hints, options, open_, cls = method_settings(method, m, run)
    raw = raw or {}
    out = {}
    for key, given in opts.items():
        value = given
        shown = f"{key}={raw.get(key, json.dumps(value))}"
        if key not in hints and not open_:
            raise unknown_setting(key, f"the {method} method", hints)
        hint = hints.get(key)
        rule = _range_rule(key)
        if rule and isinstance(value, (int, float)) and not isinstance(value, bool) and not rule[0](value):
            raise click.BadParameter(f"{shown}: {key} must be {rule[1]}", param_hint="--set")
        if not _accepts(hint, value):
            raise click.BadParameter(f"{shown}: {key} must be {_describe(hint)}", param_hint="--set")
        if isinstance(value, float) and not math.isfinite(value):
            raise click.BadParameter(f"{shown}: {key} must be a finite number", param_hint="--set")
        if key in options and value is not None:
            try:
                value = options[key].type.convert(value, options[key], None)
            except click.BadParameter as exc:
                raise click.BadParameter(f"{shown}: {exc.message}", param_hint="--set") from None
        if rule and isinstance(value, (int, float)) and not isinstance(value, bool) and not rule[0](value):
            raise click.BadParameter(f"{shown}: {key} must be {rule[1]}", param_hint="--set")
        out[key] = value
    if cls is not None:  # the config's own checks (e.g. ranges), on the defaults plus these settings
        names = {f.name for f in dataclasses.fields(cls)}
        given = {k: v for k, v in out.items() if k in names and not (k == "iterations" and v is None)}
        try:
            cls.from_json({**cls().to_json(), **given})
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--set") from None
    return out


def unknown_setting(key: str, owner: str, valid) -> click.BadParameter:
    """The one refusal of an unknown ``--set`` key, everywhere: it names the valid keys."""
    from clgs.methods.run import unknown_setting_message

    return click.BadParameter(unknown_setting_message(key, owner, valid), param_hint="--set")


def parse_settings(pairs, raw: dict | None = None) -> dict:
    """:func:`clgs.methods.settings.parse_pairs` (the one parser) with its refusal as a ``--set``
    usage error."""
    from clgs.methods.settings import SettingsError, parse_pairs

    try:
        return parse_pairs(pairs, raw)
    except SettingsError as exc:
        raise click.BadParameter(str(exc), param_hint="--set") from None


def setting_key(param: click.Parameter) -> str:
    """The ``--set`` key of a command option: its long name, ``-`` as ``_`` (``--grid-spacing``: grid_spacing)."""
    long = [o for o in param.opts if o.startswith("--")] or [param.name]
    return long[0].lstrip("-").replace("-", "_")


def option_settings(*names: str, owner: str):
    """``--set KEY=VALUE`` as another spelling of some of a command's own options (``names``: their
    ``--set`` keys, :func:`setting_key`): for a command that runs no method but has settings
    (``clgs simulate``: the scanner and the noise). A key is read as its option reads it (same
    type and checks); an unknown key is refused as everywhere (:func:`unknown_setting`); a
    setting given both ways is a usage error. Place it right under ``@click.command``."""
    import functools

    def decorate(f):
        @functools.wraps(f)
        def wrapper(*args, settings=(), **kwargs):
            if settings:
                kwargs.update(options_from_settings(click.get_current_context(), settings, names, owner))
            return f(*args, **kwargs)

        wrapper.setting_keys, wrapper.setting_owner = tuple(names), owner  # read by the docs' checks

        return click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
                            help=f"a setting of {owner} by name, the same as its option (repeatable; keys: "
                                 f"{', '.join(names)})")(wrapper)

    return decorate


def options_from_settings(ctx, pairs, names, owner) -> dict:
    """{parameter name: value} of ``--set`` pairs naming some of the command's options (``names``)."""
    raw: dict = {}
    parse_settings(pairs, raw)
    params = {setting_key(p): p for p in ctx.command.params if setting_key(p) in names}
    lower = {k.lower(): k for k in params}
    out = {}
    for key, text in raw.items():
        name = key if key in params else lower.get(key.lower())
        if name is None:
            raise unknown_setting(key, owner, names)
        param = params[name]
        if ctx.get_parameter_source(param.name) == click.core.ParameterSource.COMMANDLINE:
            raise click.UsageError(f"{name} given both as an option and with --set; give it once")
        try:
            out[param.name] = param.type_cast_value(ctx, text.strip())
        except click.BadParameter as exc:
            raise click.BadParameter(f"{key}={text}: {exc.message}", param_hint="--set") from None
        ctx.set_parameter_source(param.name, click.core.ParameterSource.COMMANDLINE)
    return out
