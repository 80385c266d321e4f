"""The built wheel carries the OpenCL sources and they compile from an installed copy.

Builds the wheel from this checkout (``python -m build --wheel --no-isolation``: hatchling is a
declared build requirement, so no network is needed), installs it with ``--no-deps`` into a fresh
virtualenv outside the checkout that sees the site-packages of the environment running the tests
(numpy, torch, pyopencl; a virtualenv's or the system's), and, from a neutral working directory,
checks that ``clgs`` and its ``cl`` folder come from that virtualenv (not from an editable install
of the checkout), then compiles every top-level ``.cl`` file with ``runtime.get_program``.
"""
import importlib.util
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

CHECK = r"""
import json, sys
from pathlib import Path
import clgs
from clgs import runtime
venv = Path(sys.prefix).resolve()
src = runtime.cl_source_dir().resolve()
files = sorted(p.name for p in src.glob("*.cl"))
failed = {}
for name in files:
    try:
        runtime.get_program(name)
    except Exception as exc:  # report every file, not just the first failure
        failed[name] = str(exc)[-2000:]
print(json.dumps({"prefix": str(venv), "clgs": str(Path(clgs.__file__).resolve()), "cl_dir": str(src),
                  "compiled": [f for f in files if f not in failed], "failed": failed,
                  "sources": sorted(p.name for p in src.iterdir())}))
"""


def _run(cmd, **kw):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kw)


def _clean_env():
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.setdefault("POCL_CACHE_DIR", str(Path.home() / ".cache" / "pocl" / "kcache"))
    return env


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    missing = [m for m in ("build", "hatchling") if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"cannot build the wheel offline: {' and '.join(missing)} not installed "
                    "(pip install build hatchling)")
    out = tmp_path_factory.mktemp("dist")
    res = _run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", str(out), str(ROOT)],
               cwd=out, env=_clean_env())
    assert res.returncode == 0, f"wheel build failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    wheels = list(out.glob("clgs-*.whl"))
    assert len(wheels) == 1, f"expected one clgs wheel in {out}, found {wheels}"
    return wheels[0]


def test_wheel_ships_every_opencl_source(wheel):
    with zipfile.ZipFile(wheel) as zf:
        shipped = {Path(n).name for n in zf.namelist() if n.startswith("clgs/cl/")}
    sources = {p.name for p in (ROOT / "cl").iterdir() if p.suffix in (".cl", ".h")}
    assert "common.h" in shipped
    assert sources <= shipped, f"missing from the wheel: {sorted(sources - shipped)}"


def test_installed_wheel_compiles_every_kernel(wheel, tmp_path):
    venv = tmp_path / "venv"
    assert ROOT not in venv.parents
    res = _run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    assert res.returncode == 0, res.stderr
    py = venv / "bin" / "python"
    # numpy, torch, pyopencl... from the environment running the tests (a virtualenv's, or the
    # system's): its site-packages go on the new one's path after the wheel's own. Plain paths in a
    # .pth file: the outer environment's own .pth files (an editable clgs among them) are not run.
    # (`venv --system-site-packages` would reach the base interpreter's packages instead, which
    # from inside a virtualenv are not the ones set up.)
    import site

    res = _run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"])
    assert res.returncode == 0, res.stderr
    outer = [p for p in (*site.getsitepackages(), site.getusersitepackages()) if os.path.isdir(p)]
    (Path(res.stdout.strip()) / "outer_environment.pth").write_text("\n".join(outer) + "\n")
    res = _run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
                "--force-reinstall", "--no-compile", str(wheel)], cwd=tmp_path, env=_clean_env())
    assert res.returncode == 0, f"pip install of the wheel failed:\n{res.stdout[-2000:]}\n{res.stderr[-2000:]}"

    work = tmp_path / "elsewhere"
    work.mkdir()
    res = _run([str(py), "-c", CHECK], cwd=work, env=_clean_env())
    assert res.returncode == 0, f"check in the virtualenv failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    info = json.loads(res.stdout.strip().splitlines()[-1])
    prefix = Path(info["prefix"])
    assert prefix == venv.resolve()
    assert prefix in Path(info["clgs"]).parents, f"clgs imported from {info['clgs']}, not from the wheel"
    assert prefix in Path(info["cl_dir"]).parents, f"OpenCL sources found at {info['cl_dir']}, not in the wheel"
    checkout_cl = sorted(p.name for p in (ROOT / "cl").glob("*.cl"))
    assert not info["failed"], "kernels that do not compile from the wheel:\n" + "\n".join(
        f"{k}: {v}" for k, v in info["failed"].items())
    assert info["compiled"] and set(checkout_cl) <= set(info["compiled"]), (checkout_cl, info["compiled"])
