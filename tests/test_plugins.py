"""Anatomy plugins: real entry-point discovery, duplicates, broken plugins, the per-anatomy CLI."""
import json
import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from clgs.anatomy import Anatomy
from clgs.anatomy.plugins import DuplicateAnatomyError, PluginWarning, Registry, UnknownAnatomyError

ROOT = Path(__file__).resolve().parents[1]
TOY = ROOT / "examples" / "toy_plugin"


def _env(*paths, **extra):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(p) for p in paths] + [str(ROOT)] +
                                        ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _clgs(args, env):
    return subprocess.run([sys.executable, "-m", "clgs.cli", *args], capture_output=True, text=True, env=env,
                          timeout=120)


@pytest.fixture(scope="module")
def toy_target(tmp_path_factory):
    """The example plugin pip-installed (no deps) into a directory put on PYTHONPATH."""
    target = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index",
                        "--quiet", "--target", str(target), str(TOY)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert (target / "clgs_toy").is_dir() and list(target.glob("clgs_toy-*.dist-info"))
    return target


def _fake_dist(site: Path, dist: str, module: str, source: str, entry: str = None):
    """A minimal installed distribution: a module plus a dist-info with an entry point."""
    (site / f"{module}.py").write_text(textwrap.dedent(source))
    info = site / f"{dist.replace('-', '_')}-1.2.3.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.2.3\n")
    (info / "entry_points.txt").write_text(f"[clgs.anatomies]\n{entry or module} = {module}\n")


PLUGIN = """
from clgs.anatomy import Anatomy
from clgs.anatomy.hookspecs import hookimpl

@hookimpl
def clgs_anatomies():
    return [Anatomy(name={name!r}, summary={summary!r})]
"""


@pytest.fixture
def on_path(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    monkeypatch.syspath_prepend(str(site))
    return site


# --------------------------------------------------------------------------------------- real install
def test_installed_example_plugin_is_discovered_by_the_cli(toy_target, tmp_path):
    env = _env(toy_target, CLGS_TOY_HOME=tmp_path / "home")
    r = _clgs(["anatomies", "--json"], env)
    assert r.returncode == 0, r.stderr
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    toy = rows["toy"]
    assert toy["package"] == "clgs-toy" and toy["version"] == "0.1.0" and toy["built"] is False
    assert toy["model_path"].startswith(str(tmp_path / "home"))
    r = _clgs(["toy", "--help"], env)
    assert r.returncode == 0, r.stderr
    for cmd in ("simulate", "reconstruct", "build-model", "evaluate", "demo", "info", "params"):
        assert f"  {cmd} " in r.stdout
    r = _clgs(["--help"], env)
    assert r.returncode == 0 and "  toy " in r.stdout


def test_listing_plugins_imports_no_torch_or_opencl(toy_target):
    code = ("import sys; from clgs.anatomy import plugins; names = plugins.anatomy_names(); "
            "print(','.join(names)); print([m for m in ('torch', 'pyopencl') if m in sys.modules])")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(toy_target), timeout=120)
    assert r.returncode == 0, r.stderr
    names, heavy = r.stdout.strip().splitlines()
    assert "toy" in names.split(",") and heavy == "[]"


# --------------------------------------------------------------------------------------- duplicates, failures
def test_two_distributions_with_the_same_anatomy_name(on_path):
    _fake_dist(on_path, "dup-alpha", "dup_alpha", PLUGIN.format(name="bone", summary="a"))
    _fake_dist(on_path, "dup-beta", "dup_beta", PLUGIN.format(name="bone", summary="b"))
    reg = Registry()
    reg.load_entry_points()
    with pytest.raises(DuplicateAnatomyError) as err:
        reg.anatomies()
    msg = str(err.value)
    assert "'bone'" in msg and "dup-alpha" in msg and "dup-beta" in msg
    # the command line reports it as an error naming both packages, without a traceback
    r = _clgs(["anatomies"], _env(on_path))
    assert r.returncode != 0
    assert "dup-alpha" in r.stderr and "dup-beta" in r.stderr and "Traceback" not in r.stderr


def test_broken_plugin_is_a_warning_and_others_keep_working(on_path):
    _fake_dist(on_path, "broken-plugin", "broken_plugin", "raise ImportError('needs libfoo 2')\n")
    _fake_dist(on_path, "good-plugin", "good_plugin", PLUGIN.format(name="goodbone", summary="works"))
    reg = Registry()
    with pytest.warns(PluginWarning, match=r"broken-plugin.*needs libfoo 2"):
        reg.load_entry_points()
    found = reg.anatomies()
    assert found["goodbone"].package == "good-plugin" and found["goodbone"].version == "1.2.3"
    r = _clgs(["anatomies"], _env(on_path))
    assert r.returncode == 0, r.stderr
    assert "goodbone" in r.stdout and "needs libfoo 2" in r.stderr
    r = _clgs(["goodbone", "info"], _env(on_path))
    assert r.returncode == 0 and "goodbone: works" in r.stdout


def test_registry_checks_what_plugins_return():
    class Good:
        def clgs_anatomies(self):
            return [Anatomy(name="knee", summary="k", version="2.0")]

    class Raises:
        def clgs_anatomies(self):
            raise RuntimeError("no data folder")

    class WrongType:
        def clgs_anatomies(self):
            return ["knee"]

    class BadNames:
        def clgs_anatomies(self):
            return [Anatomy(name="Knee Joint", summary="x"), Anatomy(name="info", summary="x"),
                    Anatomy(name="hip", summary="h")]

    from clgs.anatomy.hookspecs import hookimpl

    for cls in (Good, Raises, WrongType, BadNames):
        cls.clgs_anatomies = hookimpl(cls.clgs_anatomies)
    reg = Registry()
    reg.register(Good(), name="good", package="pkg-good", version="9")
    reg.register(Raises(), name="raises", package="pkg-raises")
    reg.register(WrongType(), name="wrong", package="pkg-wrong")
    reg.register(BadNames(), name="badnames", package="pkg-bad")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        found = reg.anatomies()
    text = "\n".join(str(w.message) for w in caught)
    assert "no data folder" in text and "pkg-raises" in text
    assert "must return a list" in text and "'Knee Joint'" in text and "clashes with the built-in" in text
    assert sorted(found) == ["hip", "knee"]
    assert found["knee"].package == "pkg-good" and found["knee"].version == "2.0"  # plugin's own version kept
    with pytest.raises(UnknownAnatomyError, match="hip, knee"):
        reg.get("femurx")

    class Dup:
        @hookimpl
        def clgs_anatomies(self):
            return [Anatomy(name="knee", summary="again")]

    reg.register(Dup(), name="dup", package="pkg-dup")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PluginWarning)  # the broken ones above warn again
        with pytest.raises(DuplicateAnatomyError, match="pkg-good.*pkg-dup|pkg-dup.*pkg-good"):
            reg.anatomies()


@pytest.mark.parametrize("name", ["import", "convert", "batch", "anatomies"])
def test_every_built_in_command_name_is_refused_as_an_anatomy(name):
    """The names the registry refuses are the command line's own commands (one table), so an
    anatomy can never be shadowed by a built-in command and silently unreachable."""
    from clgs.anatomy import plugins
    from clgs.anatomy.hookspecs import hookimpl
    from clgs.cli import COMMANDS, main

    assert plugins._RESERVED == set(COMMANDS) == set(main.list_commands(click.Context(main))) - set(
        plugins.anatomy_names())

    class Shadowed:
        @hookimpl
        def clgs_anatomies(self):
            return [Anatomy(name=name, summary="x")]

    reg = Registry()
    reg.register(Shadowed(), name="shadowed", package="pkg-shadowed")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert name not in reg.anatomies()
    assert any(f"clashes with the built-in command 'clgs {name}'" in str(w.message) for w in caught)


# --------------------------------------------------------------------------------------- the group
@pytest.fixture
def toy(toy_target, tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(toy_target))
    monkeypatch.setenv("CLGS_TOY_HOME", str(tmp_path / "home"))
    import clgs_toy

    (anatomy,) = clgs_toy.clgs_anatomies()
    anatomy.package = "clgs-toy"
    return anatomy


def test_group_info_build_and_extra_command(toy, tmp_path, monkeypatch):
    import clgs_toy

    from clgs.cli.anatomy_group import make_group

    # the wiring is under test here, not the registration: keep it short
    monkeypatch.setattr(clgs_toy, "BUILD_SETTINGS", {"registration": {"levels": [0], "iterations": [5]}})

    group = make_group(toy)
    runner = CliRunner()
    r = runner.invoke(group, ["info"])
    assert r.exit_code == 0, r.output
    assert "template  grid (40, 40, 56)" in r.output and "not built" in r.output
    r = runner.invoke(group, ["build-model", "--max-cells", "8", "--n-modes", "2"])
    assert r.exit_code == 0, r.output
    assert os.path.exists(toy.model_path)
    r = runner.invoke(group, ["info"])
    assert r.exit_code == 0, r.output
    assert "2 modes on grid" in r.output and "8 subjects" in r.output and "density atlas (40, 40, 56)" in r.output
    r = runner.invoke(group, ["params", "08"])
    assert r.exit_code == 0 and "semi_axes_mm" in json.loads(r.output)
    clash = Anatomy(name="clash", summary="x", commands=[click.Command("info")])
    with pytest.raises(click.ClickException, match="clashes"):
        make_group(clash)


def test_group_simulate_reconstruct_evaluate(toy, tmp_path):
    pytest.importorskip("clgs.ops.ct_projector")
    from clgs.cli.anatomy_group import make_group

    group = make_group(toy)
    runner = CliRunner()
    scan = tmp_path / "scan"
    r = runner.invoke(group, ["simulate", "--subject", "09", "--out", str(scan), "--views", "24", "--no-noise"])
    assert r.exit_code == 0, r.output
    from clgs.io.scan import Scan

    s = Scan.load(scan)
    assert s.n_views == 24 and s.truth.shape == (40, 40, 56) and s.meta["subject"] == "09"
    assert s.surface is not None
    r = runner.invoke(group, ["reconstruct", str(scan), "--out", str(tmp_path / "rec"), "--method", "fdk"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "rec" / "volume.npy").exists() and "psnr3d" in r.output
    rec = dict(line.split(None, 1) for line in r.output.strip().splitlines()[1:])
    assert float(rec["surface_mean_mm"]) < 1.0  # 24 noiseless views: FDK finds the bone surface
    truth = tmp_path / "truth.npy"
    import numpy as np

    np.save(truth, s.truth)
    r = runner.invoke(group, ["evaluate", str(truth), str(scan)])
    assert r.exit_code == 0, r.output
    lines = dict(line.split(None, 1) for line in r.output.strip().splitlines())
    assert float(lines["ssim3d"]) == pytest.approx(1.0, abs=1e-6)
    assert float(lines["surface_mean_mm"]) < 0.5  # the truth's own bone surface vs the true mesh
    r = runner.invoke(group, ["reconstruct", str(scan), "--out", str(tmp_path / "rec2"), "--method", "nosuch"])
    assert r.exit_code != 0 and "not available" in r.output
    # a method that takes no anatomy (R2-Gaussian) runs from the anatomy's group too
    r = runner.invoke(group, ["reconstruct", str(scan), "--out", str(tmp_path / "rec3"), "--method", "r2gs",
                              "--set", "iterations=3", "--set", "n_gaussians=200", "--set", "progress=false"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "rec3" / "volume.nii.gz").exists() and "psnr3d" in r.output


def test_generic_build_model_without_a_plugin_builder(tmp_path):
    """An anatomy that gives only a template, a population and subjects gets the generic builder."""
    import numpy as np

    from clgs.cli.anatomy_group import make_group
    from clgs.shape.model import read_metadata
    from clgs.shape.template import Subject, Template, box_grid, grid_points, mesh_from_sdf

    def blob(axes, sid):
        a = np.asarray(axes, float)
        shape, sp, org = box_grid(-a - 3, a + 3, spacing=1.5)
        v, f = mesh_from_sdf((np.linalg.norm(grid_points(shape, sp, org) / a, axis=-1) - 1) * a.min(), sp, org)
        return Subject(sid, v, f)

    axes = {"a": (14, 9, 8), "b": (16, 9, 7)}
    mean = blob((15, 9.3, 7.7), "template")
    template = Template.from_mesh(mean.vertices, mean.faces, spacing=2.5, margin=8.0, name="blob")
    anatomy = Anatomy(name="blob", summary="b", load_template=lambda: template, population=lambda: list(axes),
                      load_subject=lambda sid: blob(axes[sid], sid), model_path=str(tmp_path / "blob.npz"))
    r = CliRunner().invoke(make_group(anatomy), ["build-model", "--max-cells", "6"])
    assert r.exit_code == 0, r.output
    meta = read_metadata(tmp_path / "blob.npz")
    assert meta["population"] == ["a", "b"] and meta["has_atlas"] is False  # no CT given: no atlas
    assert "no subject had a CT volume" in meta["atlas_note"]
    r = CliRunner().invoke(make_group(anatomy), ["info"])
    assert r.exit_code == 0 and "no subject had a CT volume" in r.output


def test_methods_come_through_the_same_plugin_mechanism(monkeypatch, tmp_path):
    """A plugin provides reconstruction methods with the pluggy hook ``clgs_methods``, beside (or
    instead of) anatomies; ``clgs reconstruct --method NAME`` then runs it, and a name clash with a
    built-in method is an error naming the package."""
    import numpy as np
    from click.testing import CliRunner

    from clgs import methods
    from clgs.anatomy import hookimpl, plugins
    from clgs.cli import main
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan

    def zeros(scan, out_dir=None):
        return {"volume": np.zeros(scan.geometry.nVoxel, np.float32)}

    def installed(name, help_text, package):
        """A registry holding one plugin whose clgs_methods provides ``name``, made the process's."""
        class Provider:
            @hookimpl
            def clgs_methods(self):
                return [methods.Method(name, zeros, help=help_text)]

        reg = plugins.Registry()
        reg.register(Provider(), name=package, package=package)
        monkeypatch.setattr(plugins, "registry", lambda reload=False: reg)
        monkeypatch.setattr(methods, "_PLUGINS_SEEN", [False])

    monkeypatch.setattr(methods, "_REGISTRY", dict(methods._REGISTRY))
    installed("t-plugin-zeros", "a plugin's method", "provider-pkg")
    assert "t-plugin-zeros" in methods.names() and methods.describe()["t-plugin-zeros"] == "a plugin's method"
    geo = Geometry.default(n_views=2, n_voxel=8, n_detector=12, volume_mm=32.0)
    Scan(geo, np.zeros((2, 12, 12), np.float32)).save(tmp_path / "scan")
    res = CliRunner().invoke(main, ["reconstruct", str(tmp_path / "scan"), "--method", "t-plugin-zeros",
                                    "--out", str(tmp_path / "z.nii.gz")])
    assert res.exit_code == 0, res.output

    installed("fdk", "another fdk", "clash-pkg")
    with pytest.raises(methods.MethodError, match="clash-pkg"):
        methods.names()
