"""Helpers the CLI tests share: run a command in-process, and see which modules a fresh
interpreter loads for a command's help (the CLI must start without the heavy ones)."""
import os
import subprocess
import sys
from pathlib import Path

from click.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]


def run(*args, ok=True):
    """``clgs ARGS`` in this process; with ``ok`` its exit status must be 0. Exceptions that the
    command does not turn into a message propagate (a traceback is a failure, not an exit code)."""
    from clgs.cli import main

    res = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    if ok:
        assert res.exit_code == 0, res.output
    return res


def modules_loaded_by_help(arg_lists, packages) -> list:
    """The modules of ``packages`` that a fresh interpreter has loaded after running each argument
    list of ``arg_lists`` (help requests) through the CLI; each run must exit 0."""
    code = ("import sys\nfrom click.testing import CliRunner\nimport clgs\nimport clgs.cli\n"
            f"for args in {list(map(list, arg_lists))!r}:\n"
            "    r = CliRunner().invoke(clgs.cli.main, args)\n    assert r.exit_code == 0, r.output\n"
            f"print(','.join(sorted(m for m in sys.modules if m.split('.')[0] in {tuple(packages)!r})))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    return [m for m in out.stdout.strip().split(",") if m]
