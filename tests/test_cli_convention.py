"""One command-line convention for every ``clgs`` command (docs/commands.md, "Conventions"):
the whole command tree (built-ins, benchmarks, every installed anatomy group, every method's
options under ``clgs reconstruct``) is walked and each rule checked; then the behaviour: a quiet
run says only its result, method options stand before or after SCAN, every evaluate takes the
result first, and an unknown ``--set`` key is refused the same way everywhere."""
from __future__ import annotations

import click
import numpy as np
import pytest
from click.testing import CliRunner

from clgs.cli import main
from clgs.cli.options import FORCE_HELP

# commands that write files: each takes -o/--out (an anatomy's commands are under "<anatomy>")
WRITERS = {"simulate", "reconstruct", "evaluate", "convert", "import", "batch", "bench scaling",
           "<anatomy> simulate", "<anatomy> reconstruct", "<anatomy> demo", "<anatomy> experiment",
           "<anatomy> build-model", "<anatomy> evaluate"}
# commands that run a method (--set: its settings) or have settings of their own (simulate)
SETTERS = {"reconstruct", "batch", "simulate", "<anatomy> reconstruct", "<anatomy> demo", "<anatomy> experiment",
           "<anatomy> simulate"}
# a --no-X flag without its --X side: the off side of an option that takes a value (--figure PNG)
OFF_ONLY = {("evaluate", "--no-figure")}


def commands() -> dict:
    """'path' -> (click command, its parameters) for every command of the tree; clgs reconstruct
    once per method, with that method's options."""
    from clgs import methods
    from clgs.anatomy import plugins
    from clgs.cli.options import method_params

    anatomies = set(plugins.anatomy_names())
    out = {}

    def walk(cmd, path, parent):
        ctx = click.Context(cmd, info_name=path[-1] if path else "clgs", parent=parent)
        if isinstance(cmd, click.Group):
            for name in cmd.list_commands(ctx):
                walk(cmd.get_command(ctx, name), path + [name], ctx)
            return
        key = " ".join(["<anatomy>" if path[0] in anatomies and len(path) > 1 else path[0]] + path[1:])
        if path == ["reconstruct"]:
            for name in methods.describe():
                out[f"reconstruct --method {name}"] = (key, cmd, cmd.params + method_params(methods.get(name)))
        else:
            out[" ".join(path)] = (key, cmd, cmd.params)

    walk(main, [], None)
    return out


TREE = commands()


def options(params):
    return [p for p in params if isinstance(p, click.Option)]


def names(params) -> set:
    return {o for p in options(params) for o in p.opts + p.secondary_opts}


def test_the_walk_sees_the_whole_tree():
    keys = {k for k, _, _ in TREE.values()}
    assert keys >= WRITERS and keys >= SETTERS, sorted((WRITERS | SETTERS) - keys)
    from clgs.anatomy import plugins

    plugins.registry(reload=True)  # what is installed now (another test may have swapped the registry)
    installed, tree = plugins.anatomy_names(), commands()  # femur and patella where their packages load
    assert installed and all(any(path.startswith(f"{a} ") for path in tree) for a in installed)
    assert len([p for p in TREE if p.startswith("reconstruct --method")]) >= 4


@pytest.mark.parametrize("path", sorted(TREE))
def test_the_convention(path):
    key, cmd, params = TREE[path]
    found = names(params)
    writes = key in WRITERS or any(p.name in ("out", "out_path", "json_out", "plot") for p in options(params))
    if writes:
        assert {"-o", "--out"} <= found, f"clgs {path} writes files but has no -o/--out"
    if key in SETTERS or ("--method" in found and not path.startswith("bench")):
        assert "--set" in found, f"clgs {path} runs a method or has settings but takes no --set"
    for p in options(params):
        if "--views" in p.opts:
            t = p.type
            counts = (isinstance(t, click.IntRange) and t.min is not None and t.min >= 1) \
                or t.name == "count[,count...]"
            assert counts, f"clgs {path} --views is not a count of views ({t.name})"
        if "--force" in p.opts:
            assert p.is_flag and (p.help or "").startswith(FORCE_HELP), f"clgs {path} --force: {p.help!r}"
        for o in p.opts:
            if o.startswith("--no-") and (key, o) not in OFF_ONLY:
                pytest.fail(f"clgs {path}: {o} without its --{o[5:]} side; declare --{o[5:]}/{o}")
        if p.secondary_opts:
            assert all(s.startswith("--no-") for s in p.secondary_opts if s != "--noiseless"), \
                f"clgs {path}: a switch's off side is --no-X: {p.secondary_opts}"
    if key == "evaluate" or key == "<anatomy> evaluate":
        args = [p.human_readable_name for p in params if isinstance(p, click.Argument)]
        assert args[0] == "VOLUME" and args[1] in ("TRUTH", "SCAN"), args


def test_the_root_has_quiet_and_verbose():
    assert {"-q", "--quiet", "-v", "--verbose"} <= names(main.params)


# ------------------------------------------------------------------------------------ behaviour
def cli(*args, ok=True):
    res = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    if ok:
        assert res.exit_code == 0, res.output
    return res


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A 24^3 ball and its 6-view scan (made quietly)."""
    d = tmp_path_factory.mktemp("convention")
    z, y, x = np.mgrid[:24, :24, :24] - 11.5
    np.save(d / "ball.npy", ((x * x + y * y + z * z) < 64).astype(np.float32) * 0.02)
    res = cli("--quiet", "simulate", d / "ball.npy", "--spacing", 1, "--views", 6, "--detector", 32,
              "-o", d / "scan")
    assert res.output.strip().splitlines() == [res.output.strip()] and res.output.startswith(f"wrote {d / 'scan'}")
    return d


def test_quiet_says_only_the_result(small, tmp_path):
    loud = cli("reconstruct", small / "scan", "-o", tmp_path / "a.nii.gz")
    quiet = cli("--quiet", "reconstruct", small / "scan", "-o", tmp_path / "b.nii.gz")
    lines = quiet.output.strip().splitlines()  # stdout and stderr together: no bar, no announcement
    assert len(lines) == 2 and lines[0].startswith("fdk: ") and "PSNR" in lines[0], quiet.output
    assert lines[1] == f"wrote {tmp_path / 'b.nii.gz'}"
    assert quiet.stderr == "" and len(loud.output.splitlines()) > len(lines)
    sim = cli("-q", "simulate", small / "ball.npy", "--spacing", 1, "--views", 4, "--detector", 24,
              "-o", tmp_path / "s")
    assert sim.output.strip().splitlines() == [sim.output.strip()] and sim.stderr == ""


def test_progress_bars_follow_quiet(monkeypatch):
    from clgs.progress import progress_bar, progress_enabled

    monkeypatch.setenv("CLGS_VERBOSITY", "quiet")
    assert not progress_enabled() and progress_bar(total=3).disable
    monkeypatch.setenv("CLGS_VERBOSITY", "normal")
    assert progress_enabled()


def test_verbose_says_the_device_and_the_settings(small, tmp_path):
    res = cli("--verbose", "reconstruct", small / "scan", "-m", "sart", "--iterations", 2, "-o", tmp_path / "v.npy")
    assert "device: " in res.stderr and 'settings: {"iterations": 2}' in res.stderr and "timings: " in res.stderr
    assert "both" in cli("-q", "-v", "info", ok=False).output


def test_method_options_before_or_after_scan(small, tmp_path):
    cli("reconstruct", "--method", "sart", "--iterations", 2, small / "scan", "-o", tmp_path / "before.npy")
    cli("reconstruct", small / "scan", "--method", "sart", "-o", tmp_path / "after.npy", "--iterations", 2)
    cli("reconstruct", "-m", "sart", "--set", "iterations=2", small / "scan", "-o", tmp_path / "set.npy")
    a, b, c = (np.load(tmp_path / f"{n}.npy") for n in ("before", "after", "set"))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    bad = cli("reconstruct", "--method", "sart", "--bogus", 2, small / "scan", "-o", tmp_path / "x.npy", ok=False)
    assert bad.exit_code == 2 and "--iterations, --subsets, --relaxation" in bad.output


def test_every_evaluate_takes_the_result_first(small, tmp_path):
    cli("-q", "reconstruct", small / "scan", "-o", tmp_path / "run")
    ok = cli("evaluate", tmp_path / "run", small / "scan", "--no-figure")
    assert "PSNR" in ok.output
    assert cli("evaluate", tmp_path / "run", "--truth", small / "scan", "--no-figure").output == ok.output
    from clgs.anatomy import plugins

    for command in (["evaluate"], *([a, "evaluate"] for a in plugins.anatomy_names())):
        wrong = cli(*command, small / "scan", tmp_path / "run", ok=False)
        assert wrong.exit_code == 2 and "the result first, then the truth" in wrong.output and "swap" in wrong.output


def test_one_settings_parser_and_one_refusal(small, tmp_path):
    import clgs.cohort.batch as batch
    from clgs.methods.settings import SettingsError, parse_pairs

    assert not hasattr(batch, "parse_setting_pairs") and batch.parse_pairs is parse_pairs
    assert parse_pairs(["short-scan=off", "iterations=3", "filter=hann"]) == {
        "short_scan": "off", "iterations": 3, "filter": "hann"}
    with pytest.raises(SettingsError, match="KEY=VALUE"):
        parse_pairs(["iterations"])
    rec = cli("reconstruct", small / "scan", "--set", "bogus=1", "-o", tmp_path / "r.npy", ok=False)
    sim = cli("simulate", small / "ball.npy", "--spacing", 1, "--set", "bogus=1", "-o", tmp_path / "s", ok=False)
    for res, owner in ((rec, "the fdk method"), (sim, "clgs simulate")):
        assert res.exit_code == 2 and f"unknown setting 'bogus' for {owner}; valid keys: " in res.output
    assert "filter, short_scan" in rec.output and "I0" in sim.output


def test_simulate_takes_its_settings_with_set(small, tmp_path):
    cli("-q", "simulate", small / "ball.npy", "--spacing", 1, "--detector", 24, "--set", "views=3",
        "--set", "noise=off", "-o", tmp_path / "s")
    from clgs.io.scan import Scan

    scan = Scan.load(tmp_path / "s")
    assert scan.n_views == 3 and scan.meta["acquisition"]["noise"] is False
    twice = cli("simulate", small / "ball.npy", "--spacing", 1, "--views", 3, "--set", "views=4", "-o",
                tmp_path / "t", ok=False)
    assert twice.exit_code == 2 and "give it once" in twice.output
