"""``clgs.methods.run.run_method``: the one way a method runs, from Python, ``clgs reconstruct``,
``clgs <anatomy> reconstruct``, ``clgs batch`` and the experiment; one answer to "does method M take
setting K?" and one refusal of an unknown key."""
import numpy as np
import pytest
from click.testing import CliRunner
from sphere_scan import sphere_scan
from test_shape_guided import _scan, _small, _tiny_anatomy, atlas, shape_model, template  # noqa: F401

import clgs
from clgs import methods
from clgs.cli import main
from clgs.methods.run import UnknownSettingError, accepted_settings, check_method_settings, run_method

N = 12


@pytest.fixture(scope="module")
def scan():
    return sphere_scan(N, 5, 16, 48.0, 16)


@pytest.fixture(scope="module")
def scan_dir(scan, tmp_path_factory):
    folder = tmp_path_factory.mktemp("run_method") / "scan"
    scan.save(folder)
    return folder


TINY = {"fdk": {}, "sart": {"iterations": 1}, "r2gs": {"iterations": 3, "n_gaussians": 300, "log_every": 0}}


def test_public_names():
    assert clgs.run_method is run_method


@pytest.mark.parametrize("name", sorted(TINY))
def test_every_classical_and_gaussian_method_runs(scan, name):
    out = run_method(name, scan, None, TINY[name], seed=0, progress=False)
    vol = np.asarray(out["volume"])
    assert vol.shape == tuple(scan.geometry.nVoxel) and np.all(np.isfinite(vol))
    # the same call straight to the registered callable gives the same volume, bit for bit
    direct = methods.get(name).callable()(scan, None, **TINY[name], **(
        {"seed": 0, "progress": False} if name == "r2gs" else {"progress": False} if name == "sart" else {}))
    assert np.array_equal(vol, np.asarray(direct["volume"]))


def test_the_shape_method_runs_with_its_anatomy(template, shape_model, atlas):  # noqa: F811
    anatomy = _tiny_anatomy(template, shape_model, atlas)
    sc = _scan(template, alpha=(0.8, -0.5), shape_model=shape_model)
    out = run_method("shape", sc, None, {"iterations": 5, **_small()}, anatomy=anatomy, seed=0)
    assert np.asarray(out["volume"]).shape == tuple(sc.geometry.nVoxel)
    assert out["result"].log.rows is not None


def test_every_registered_method_is_covered():
    assert set(methods.names()) >= set(TINY) | {"shape"}
    for name in methods.names():
        assert isinstance(accepted_settings(name), dict)


def test_accepted_settings_answer_once():
    assert set(accepted_settings("fdk")) == {"filter", "short_scan"}
    assert {"iterations", "subsets", "relaxation", "progress"} <= set(accepted_settings("sart"))
    assert {"iterations", "n_gaussians", "seed", "resume", "lambda_tv"} <= set(accepted_settings("r2gs"))
    assert {"shape_prior", "density_prior", "level"} <= set(accepted_settings("shape"))


MESSAGE = "unknown setting 'bogus' for the sart method; valid keys: iterations, progress, relaxation, subsets"


def test_unknown_setting_refused_from_python(scan):
    with pytest.raises(UnknownSettingError) as exc:
        run_method("sart", scan, None, {"bogus": 1})
    assert str(exc.value) == MESSAGE
    assert isinstance(exc.value, clgs.ClgsError)
    with pytest.raises(UnknownSettingError):
        check_method_settings("sart", {"iterations": 1, "bogus": 1})


def test_unknown_setting_refused_the_same_from_the_cli(scan_dir, tmp_path):
    res = CliRunner().invoke(main, ["reconstruct", "--method", "sart", "--set", "bogus=1", "-o",
                                    str(tmp_path / "v.npy"), str(scan_dir)])
    assert res.exit_code == 2 and MESSAGE in " ".join(res.output.split())


def test_unknown_setting_refused_the_same_from_a_batch(scan_dir, tmp_path):
    from clgs.cohort.batch import run_batch
    from clgs.errors import InputError

    with pytest.raises(InputError) as exc:
        run_batch([{"scan": str(scan_dir), "method": "sart", "settings": ["bogus=1"]}], tmp_path / "b",
                  progress=False)
    assert MESSAGE in str(exc.value)
    assert not (tmp_path / "b").exists()  # refused before any run


def test_resume_gives_iterations_none_and_a_method_without_checkpoints_refuses(scan, monkeypatch):
    seen = {}

    def fake(scan, out_dir=None, iterations=100, resume=False, progress=True):
        seen.update(iterations=iterations, resume=resume, progress=progress)
        return {"volume": np.zeros(3)}

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", fake))
    run_method("fake", scan, "somewhere", resume=True, progress=False)
    assert seen == {"iterations": None, "resume": True, "progress": False}
    run_method("fake", scan, "somewhere", {"iterations": 7}, resume=True)
    assert seen["iterations"] == 7
    with pytest.raises(methods.MethodError, match="cannot resume"):
        run_method("fdk", scan, None, resume=True)


@pytest.fixture
def calls(monkeypatch):
    """run_method, recorded: (name, settings) of each call, the real run done."""
    import clgs.methods.run as run_module

    real, seen = run_module.run_method, []

    def spy(name, *args, **kwargs):
        seen.append((getattr(name, "name", name), args[2] if len(args) > 2 else kwargs.get("settings")))
        return real(name, *args, **kwargs)

    monkeypatch.setattr(run_module, "run_method", spy)
    return seen


def test_clgs_reconstruct_calls_run_method(scan_dir, tmp_path, calls):
    res = CliRunner().invoke(main, ["reconstruct", "--method", "sart", "--iterations", "1", "-o",
                                    str(tmp_path / "v.npy"), str(scan_dir)])
    assert res.exit_code == 0, res.output
    assert calls == [("sart", {"iterations": 1})]


def test_a_batch_calls_run_method(scan_dir, tmp_path, calls):
    from clgs.cohort.batch import run_batch

    run_batch([{"scan": str(scan_dir), "method": "fdk", "settings": ["filter=hann"]}], tmp_path / "b", progress=False)
    assert calls == [("fdk", {"filter": "hann"})]


def test_the_experiment_calls_run_method(scan, calls):
    from clgs import experiment

    out = experiment._run_one("fdk", scan, None, 10, 0, False, {})
    assert calls == [("fdk", {})]
    assert np.array_equal(out["volume"], np.asarray(run_method("fdk", scan)["volume"], np.float32))


def test_anatomy_reconstruct_calls_run_method(scan, calls, template, shape_model, atlas):  # noqa: F811
    from clgs.cli.anatomy_group import run_reconstruct

    anatomy = _tiny_anatomy(template, shape_model, atlas)
    run_reconstruct(scan, anatomy, "fdk", filter="hann")
    assert calls == [("fdk", {"filter": "hann"})]


def test_a_closing_given_reaches_a_method_that_writes_its_own_bone_surface(template, shape_model, atlas,  # noqa: F811
                                                                           tmp_path):
    """``surface_closing=`` goes to a method that writes its own bone surface (the shape-guided
    one): its surface.json names the closing given, not the anatomy's (the tiny anatomy asks for
    none). A method that writes its own surface but takes no closing is refused before it runs:
    its surface would not be the one asked for."""
    import json

    anatomy = _tiny_anatomy(template, shape_model, atlas)
    sc = _scan(template, alpha=(0.8, -0.5), shape_model=shape_model)
    run_method("shape", sc, tmp_path / "a", {"iterations": 5, **_small()}, anatomy=anatomy, seed=0,
               surface_closing=2)
    record = json.loads((tmp_path / "a" / "surface.json").read_text())
    assert record["surface_closing_max_voxels"] == 2 and record["surface_closing_voxels"] in (0, 1, 2)
    ran = []

    def own_surface(scan, out_dir=None, surface_level=None):
        ran.append(scan)
        return {"volume": np.zeros(scan.geometry.nVoxel, np.float32)}

    methods.register(methods.Method("own_surface_t", own_surface, help="test"), replace=True)
    with pytest.raises(methods.MethodError, match="takes no surface closing"):
        run_method("own_surface_t", sc, None, surface_closing=1)
    assert not ran
    with pytest.raises(clgs.errors.InputError, match="0 to 8"):
        run_method("shape", sc, None, {"iterations": 1, **_small()}, anatomy=anatomy, surface_closing=9)
