"""``KEY=VALUE`` settings of a method, as ``--set`` and a batch list's ``settings`` column give
them: the one parser of the project (the command line, :mod:`clgs.cohort.batch` and the docs'
checks all read settings through :func:`parse_pairs`).

A value is read as JSON when it is JSON (``3``, ``0.5``, ``true``, ``[1, 2]``, ``null``), else
kept as the string typed (``filter=hann``). Keys take ``-`` or ``_`` (``short-scan`` is
``short_scan``). Whether the method takes a key is checked where the method is known
(:func:`clgs.cli.settings.check_settings`).
"""
from __future__ import annotations

import json

from clgs.errors import InputError


class SettingsError(InputError):
    """A setting that does not read ``KEY=VALUE``."""


def parse_pairs(pairs, raw: dict | None = None) -> dict:
    """``KEY=VALUE`` strings -> {key: JSON value, else the string}; ``raw`` (if given) gets each
    value as typed, for messages that quote the user's own words."""
    out = {}
    for p in pairs:
        key, sep, text = str(p).partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key:
            raise SettingsError(f"expected KEY=VALUE, got {p!r}")
        if raw is not None:
            raw[key] = text
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out
