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

from clgs.anatomy import Anatomy, hookimpl
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

    from clgs.anatomy import plugins

    reg = Registry()  # the toy plugin registered in-process, as its entry point would be
    reg.register(clgs_toy, name="toy", package="clgs-toy", version="0.1.0")
    monkeypatch.setattr(plugins, "_default", reg)
    return reg.get("toy")


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
    with pytest.warns(DeprecationWarning):  # the old way to add commands, still read
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


# --------------------------------------------------------------------------------------- the typed record
def test_scene_checks_its_settings_and_reads_like_the_old_dict():
    from clgs.anatomy import Scene, SceneError

    s = Scene(mode="cone", DSO=1000, DSD=1500, nDetector=[96, 128], dDetector=(2, 2), n_views=40, surface_level=0.03)
    assert s.DSO == 1000.0 and s.nDetector == (96, 128) and isinstance(s.nDetector[0], int)
    assert s.get("n_views", 50) == 40 and s.get("arc_deg", 180.0) == 180.0 and "nVoxel" not in s
    assert dict(s) == {"mode": "cone", "DSO": 1000.0, "DSD": 1500.0, "nDetector": (96, 128),
                       "dDetector": (2.0, 2.0), "n_views": 40, "surface_level": 0.03}
    assert Scene.from_dict(dict(s)) == s and Scene.from_dict(None) == Scene()
    bad = [({"mode": "fan"}, "'cone' or 'parallel'"), ({"DSO": 1500, "DSD": 1000}, "DSD .* must be larger than DSO"),
           ({"nDetector": (96,)}, r"'nDetector' must be 2 numbers \(V, U pixels\)"),
           ({"nVoxel": (8, 8, 8.5)}, "whole number"), ({"n_views": 0}, "'n_views' must be positive"),
           ({"arc_deg": 400}, r"\(0, 360\]"), ({"density": float("nan")}, "finite"),
           ({"surface_level": "0.03"}, "must be a number"), ({"dVoxel": 2.0}, "3 numbers")]
    for settings, match in bad:
        with pytest.raises(SceneError, match=match):
            Scene.from_dict(settings)
    with pytest.raises(SceneError, match="unknown scene setting.*'n_view'.*valid: mode, DSO, DSD") as err:
        Scene.from_dict({"n_view": 10})
    assert isinstance(err.value, ValueError)


def test_anatomy_record_is_checked_when_made():
    from clgs.anatomy import AnatomyError, Scene, SceneError

    a = Anatomy(name="knee", summary="k", scene={"n_views": 12, "surface_level": 0.02})  # an old dict-style plugin
    assert isinstance(a.scene, Scene) and a.scene.n_views == 12 and Anatomy(name="x", summary="y").scene == Scene()
    with pytest.raises(AnatomyError, match=r"load_template must be a callable \(\) -> Template or None, got str"):
        Anatomy(name="knee", summary="k", load_template="template.npz")
    with pytest.raises(TypeError, match=r"load_subject must be a callable \(subject_id\) -> Subject"):
        Anatomy(name="knee", summary="k", load_subject=42)
    with pytest.raises(SceneError, match="valid: mode"):
        Anatomy(name="knee", summary="k", scene={"views": 5})
    with pytest.raises(SceneError, match="must be a clgs.anatomy.Scene or a dict"):
        Anatomy(name="knee", summary="k", scene=[("n_views", 5)])
    with pytest.raises(AnatomyError, match="summary must be a string"):
        Anatomy(name="knee", summary=None)
    with pytest.warns(DeprecationWarning, match="register_anatomy_commands"):
        Anatomy(name="knee", summary="k", commands=[click.Command("extra")])


def test_scene_level_reaches_the_bone_level_rule():
    from clgs.anatomy.bone_level import choose_level

    level = choose_level(anatomy=Anatomy(name="knee", summary="k", scene={"surface_level": 0.025}))
    assert level.value == 0.025 and level.source == "scene"
    assert choose_level(anatomy=Anatomy(name="knee", summary="k")) is None


def test_anatomy_parts_one_type_in():
    import numpy as np

    from clgs.anatomy import AnatomyParts
    from clgs.errors import InputError
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan
    from clgs.methods.shape_guided import reconstruct_shape_guided

    template = object()
    loaded = AnatomyParts.of(Anatomy(name="knee", summary="k", load_template=lambda: template))
    assert loaded.template is template and loaded.shape_model is None and loaded.atlas is None
    assert loaded.anatomy.name == "knee" and tuple(loaded) == (template, None, None)
    assert AnatomyParts.of(loaded) is loaded
    with pytest.raises(InputError, match="provides no template"):
        AnatomyParts.of(Anatomy(name="knee", summary="k"))
    with pytest.raises(InputError, match="needs a template"):
        AnatomyParts(None)
    geo = Geometry.default(n_views=2, n_voxel=8, n_detector=12, volume_mm=32.0)
    scan = Scan(geo, np.zeros((2, 12, 12), np.float32))
    for wrong in [(template, None, None), "femur", None]:
        with pytest.raises(TypeError, match=r"Anatomy or clgs.anatomy.AnatomyParts, got .*AnatomyParts\(template"):
            reconstruct_shape_guided(scan, wrong, iterations=1, progress=False)


def test_population_anatomy_is_one_declarative_call():
    """The built-in femur and patella are each one population_anatomy call; a setting given in the
    scene beyond the scanner's sizing (a surface level) is kept, and wrong ids are refused."""
    import clgs_patella

    from clgs.anatomy import PopulationAnatomy, Scene, population_anatomy

    assert isinstance(clgs_patella.PLUGIN, PopulationAnatomy)
    (anatomy,) = clgs_patella.clgs_anatomies()
    assert anatomy.name == "patella" and anatomy.population_model is clgs_patella.population_model()
    assert anatomy.scene.nVoxel == clgs_patella.SHAPE and anatomy.scene.dDetector == (2.0, 2.0)
    kw = dict(name="kneecap", summary="s", version="1", data_dir=clgs_patella.DATA_DIR,
              file_pattern="patella_left_LLP26_subject{id}.npz", ids=clgs_patella.SUBJECTS[:4], test_ids=["03"],
              shape=(16, 72, 72), spacing_mm=2.0, params=clgs_patella.params, frame_offset=clgs_patella.FRAME_OFFSET)
    mine = population_anatomy(scene=Scene(n_views=8, arc_deg=120, surface_level=0.02), **kw).anatomy()
    assert mine.scene.surface_level == 0.02 and mine.scene.n_views == 8 and mine.scene.nVoxel == (16, 72, 72)
    assert mine.population() == ["00", "01", "02"]
    with pytest.raises(ValueError, match=r"held-out ids \['99'\]"):
        population_anatomy(**dict(kw, test_ids=["99"]))


# --------------------------------------------------------------------------------------- commands by hook
def test_a_plugin_adds_commands_through_the_hooks(monkeypatch):
    """``register_commands(cli)`` adds to ``clgs``, ``register_anatomy_commands(anatomy, group)`` to
    one anatomy's group; a name of a built-in or generic command is refused with a warning."""
    from clgs.anatomy import hookimpl, plugins
    from clgs.cli import main

    @click.command("hello")
    def hello():
        """Say hello."""
        click.echo("hello from a plugin")

    @click.command("knee-stats")
    def knee_stats():
        click.echo("knee statistics")

    class Knee:
        @hookimpl
        def clgs_anatomies(self):
            return [Anatomy(name="knee", summary="a knee")]

        @hookimpl
        def register_commands(self, cli):
            cli.add_command(hello)
            cli.add_command(click.Command("reconstruct"))  # a built-in's name: refused

        @hookimpl
        def register_anatomy_commands(self, anatomy, group):
            if anatomy.name == "knee":
                group.add_command(knee_stats)
                group.add_command(click.Command("info", help="shadows the generic one"))  # refused

    class Broken:
        @hookimpl
        def register_commands(self, cli):
            cli.add_command(click.Command("half-added"))
            raise RuntimeError("no config file")

    reg = Registry()
    reg.register(Knee(), name="knee", package="pkg-knee")
    reg.register(Broken(), name="broken", package="pkg-broken")
    monkeypatch.setattr(plugins, "_default", reg)
    monkeypatch.setattr(main, "commands", dict(main.commands))  # the process's root group is left as it was
    runner = CliRunner()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = runner.invoke(main, ["hello"])
        assert r.exit_code == 0 and r.output == "hello from a plugin\n", r.output
        r = runner.invoke(main, ["--help"])
        assert "  hello " in r.output and "half-added" not in r.output
        r = runner.invoke(main, ["knee", "knee-stats"])
        assert r.exit_code == 0 and r.output == "knee statistics\n", r.output
        r = runner.invoke(main, ["knee", "info"])
        assert r.exit_code == 0 and "knee: a knee" in r.output, r.output  # still the generic info
    text = "\n".join(str(w.message) for w in caught)
    assert "pkg-knee" in text and "'reconstruct' clashes with the command 'clgs reconstruct'" in text
    assert "'info' clashes with the command 'clgs knee info'" in text
    assert "pkg-broken" in text and "no config file" in text
    assert main.get_command(click.Context(main), "reconstruct").name == "reconstruct"


# --------------------------------------------------------------------------------------- methods
METHOD_PLUGIN = """
import numpy as np
from clgs.anatomy import hookimpl
from clgs.methods import Method

def run(scan, out_dir=None):
    return {{"volume": np.full(scan.geometry.nVoxel, 0.5, np.float32)}}

@hookimpl
def register_methods(register):
    register(Method({name!r}, "{module}:run", help="a plugin's method"))
"""


@pytest.fixture
def method_state(monkeypatch):
    """The method registry as it is, restored after the test."""
    from clgs.methods import registry

    for attr in ("_REGISTRY", "_LAZY", "PROVIDERS"):
        monkeypatch.setattr(registry, attr, dict(getattr(registry, attr)))
    monkeypatch.setattr(registry, "_PLUGINS_SEEN", [False])
    monkeypatch.setattr(registry, "_MANAGER", [])
    return registry


def _fake_method_dist(site: Path, dist: str, module: str, source: str):
    (site / f"{module}.py").write_text(textwrap.dedent(source))
    info = site / f"{dist.replace('-', '_')}-2.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 2.0\n")
    (info / "entry_points.txt").write_text(f"[clgs.methods]\n{module} = {module}\n")


def test_a_method_plugin_comes_through_its_own_group(on_path, method_state, tmp_path):
    """A package with an entry point in ``clgs.methods`` whose module implements
    ``register_methods(register)``: ``clgs reconstruct --method NAME`` runs it; the built-ins come
    through the same hook (their provider is clgs)."""
    import numpy as np

    from clgs import methods
    from clgs.cli import main
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan

    _fake_method_dist(on_path, "half-method", "half_method", METHOD_PLUGIN.format(name="t-half", module="half_method"))
    assert "t-half" in methods.names() and methods.describe()["t-half"] == "a plugin's method"
    assert method_state.PROVIDERS["t-half"] == "half-method" and method_state.PROVIDERS["fdk"] == "clgs"
    geo = Geometry.default(n_views=2, n_voxel=8, n_detector=12, volume_mm=32.0)
    Scan(geo, np.zeros((2, 12, 12), np.float32)).save(tmp_path / "scan")
    r = CliRunner().invoke(main, ["reconstruct", str(tmp_path / "scan"), "--method", "t-half",
                                  "--out", str(tmp_path / "half.npy")])
    assert r.exit_code == 0, r.output
    assert np.all(np.load(tmp_path / "half.npy") == 0.5)


def test_method_plugins_that_clash_or_break(on_path, method_state):
    from clgs import methods

    _fake_method_dist(on_path, "clash-method", "clash_method", METHOD_PLUGIN.format(name="fdk", module="clash_method"))
    with pytest.raises(methods.MethodError, match="'fdk': package 'clgs' and plugin package 'clash-method'"):
        methods.names()

    manager = method_state.MethodPlugins()

    class WrongRecord:
        @hookimpl
        def register_methods(self, register):
            register("not a method")

    with pytest.warns(PluginWarning, match=r"pkg-wrong.*register\(\) takes clgs.methods.Method records, got str"):
        manager.register_plugin(WrongRecord(), name="wrong", package="pkg-wrong")


def test_the_deprecated_clgs_methods_hook_still_works(monkeypatch, method_state):
    from clgs import methods
    from clgs.anatomy import plugins

    class Old:
        @hookimpl
        def clgs_methods(self):
            return [methods.Method("t-old", lambda scan, out_dir=None: {}, help="an old plugin's method")]

    reg = Registry()
    reg.register(Old(), name="old", package="pkg-old")
    monkeypatch.setattr(plugins, "registry", lambda reload=False: reg)
    with pytest.warns(DeprecationWarning, match="pkg-old.*register_methods"):
        assert "t-old" in methods.names()

