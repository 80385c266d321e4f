"""The built-in commands of ``clgs``: name -> "module:attribute" of a click command.

One table, read by the command line (which imports a command only when it runs) and by the
plugin registry (an anatomy may not take a built-in command's name, or ``clgs NAME`` could not
reach it). Plain strings: importing this module loads nothing.
"""
from __future__ import annotations

BUILTIN_COMMANDS = {
    "info": "clgs.cli.info:info",
    "bench": "clgs.cli.bench:bench",
    "simulate": "clgs.cli.simulate:simulate",
    "reconstruct": "clgs.cli.reconstruct:reconstruct",
    "evaluate": "clgs.cli.evaluate:evaluate",
    "anatomies": "clgs.cli.anatomies:anatomies",
    "import": "clgs.cli.import_raw:import_raw",
    "convert": "clgs.cli.convert:convert",
    "batch": "clgs.cli.batch:batch",
}
