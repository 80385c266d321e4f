"""The public Python API (``clgs.NAME``) and the one error base class."""
import importlib
import inspect
import json
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import clgs
from clgs.errors import ClgsError

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", clgs.__all__)
def test_every_public_name_loads_and_is_documented(name):
    value = getattr(clgs, name)
    assert (inspect.getdoc(value) or "").strip(), f"clgs.{name} has no docstring"
    exec(f"from clgs import {name}", {})


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError):
        clgs.no_such_name  # noqa: B018


def test_import_clgs_stays_light():
    code = ("import sys, clgs\nassert clgs.__version__\n"
            "print([m for m in ('torch', 'pyopencl', 'numpy') if m in sys.modules])")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


# (every error clgs defines is one, the OpenCL set-up's NoOpenCLDevice included)
NOT_INPUT_ERRORS: set = set()


def test_every_error_clgs_defines_is_a_clgs_error():
    found = []
    for info in pkgutil.walk_packages(clgs.__path__, "clgs."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if (inspect.isclass(obj) and issubclass(obj, Exception) and not issubclass(obj, Warning)
                    and obj.__module__ == info.name
                    and f"{info.name}.{name}" not in NOT_INPUT_ERRORS):
                found.append(obj)
    assert len(found) >= 12
    wrong = [f"{c.__module__}.{c.__name__}" for c in found if not issubclass(c, ClgsError)]
    assert not wrong, f"errors outside ClgsError: {wrong}"


def test_type_checkers_see_every_public_name():
    """The lazy names are spelled out under TYPE_CHECKING (for mypy, pyright and editors), each the
    object the lazy loading gives, and the package says it is typed (py.typed)."""
    import ast

    tree = ast.parse((ROOT / "clgs" / "__init__.py").read_text())
    seen = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "_TYPE_CHECKING":
            for stmt in node.body:
                seen |= {a.asname or a.name for a in stmt.names}
    assert seen == set(clgs.__all__)
    assert (ROOT / "clgs" / "py.typed").is_file()


def test_importing_clgs_changes_nothing_in_the_process():
    """No environment variable is set by importing clgs, its runtime or its CLI; the drivers'
    settings arrive when clgs first lists the OpenCL devices (a user's own values kept)."""
    # (pyopencl itself sets PYOPENCL_HOME when it is imported: not clgs's doing)
    code = ("import os, json\nimport pyopencl\nbefore = dict(os.environ)\n"
            "import clgs, clgs.runtime, clgs.cli, clgs.io.volume\n"
            "after_import = dict(os.environ)\nclgs.runtime.candidates()\n"
            "print(json.dumps([after_import == before, sorted(set(os.environ) - set(before)),"
            " os.environ.get('POCL_AFFINITY')]))")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("POCL_", "OMP_", "OCL_ICD", "PYOPENCL"))}
    env.update(PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), POCL_AFFINITY="0")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    unchanged, added, affinity = json.loads(out.stdout.strip().splitlines()[-1])
    assert unchanged, "importing clgs set environment variables"
    assert "OMP_WAIT_POLICY" in added and "POCL_MAX_PTHREAD_COUNT" in added and "PYOPENCL_NO_CACHE" not in added
    assert affinity == "0"  # the user's own setting wins
