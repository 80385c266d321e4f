"""The README and the pages under docs/ stay true to the code.

* The README stays short (a newcomer's page; the rest lives in docs/).
* Every relative link (and image) in README.md and docs/*.md names a file that exists, and an
  anchor (``page.md#section``) names a heading of that page.
* Every ``clgs ...`` line in a shell code block names commands, options, values and ``--set`` keys
  that exist: each line goes through the click command tree's own option parser (``clgs.cli.main``,
  anatomy groups from ``clgs.cli.anatomy_group.make_group`` for every installed anatomy, a
  method's options for ``clgs reconstruct --method NAME``), and each value through its option's
  type (paths excepted: the files named in the docs are examples).
* The README's own-CT commands run as written on a small CT.
"""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import click
import pytest
from cli_helpers import run

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
README_MAX_LINES = 320

# Pages that other work adds beside these docs; docs/index.md lists them already. Only the
# index may link to them while they are missing.
FUTURE_PAGES = {"outputs.md", "dicom.md", "calibration.md", "peers.md"}

# Placeholders the checker resolves: a command position holding ANATOMY_PLACEHOLDER stands for
# every installed anatomy; a value holding SHELL_VARIABLE (a loop variable, e.g. ``$p``) is not
# type-checked. There are no other exceptions.
ANATOMY_PLACEHOLDER = "<anatomy>"
SHELL_VARIABLE = "$"

SHELL_LANGUAGES = {"", "bash", "sh", "shell", "console"}
SEPARATORS = {"&&", "||", "|", ";"}
SHELL_WORDS = {"do", "then", "else", "time"}
_UNSET = getattr(click.core, "UNSET", object())  # click's "not given" (8.3 on; older ones give None)


def doc_files() -> list:
    return [README] + sorted(DOCS.glob("*.md"))


# ---------------------------------------------------------------- markdown


def code_blocks(text: str):
    """(language, first line number, lines) of every fenced code block."""
    block, lang, start = None, "", 0
    for number, line in enumerate(text.splitlines(), 1):
        fence = re.match(r"^\s*```\s*([\w+-]*)\s*$", line)
        if fence and block is None:
            block, lang, start = [], fence.group(1).lower(), number + 1
        elif fence:
            yield lang, start, block
            block = None
        elif block is not None:
            block.append(line)


def prose(text: str, code_spans: bool = False) -> str:
    """The text without fenced blocks (where neither links nor headings are), and without inline
    code unless ``code_spans``."""
    out, inside = [], False
    for line in text.splitlines():
        if re.match(r"^\s*```", line):
            inside = not inside
            continue
        if not inside:
            out.append(line if code_spans else re.sub(r"`[^`]*`", "", line))
    return "\n".join(out)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: the rendered text, lower case, punctuation dropped, spaces
    as hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = text.replace("`", "").strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set:
    seen: dict = {}
    out = set()
    for line in prose(path.read_text(), code_spans=True).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def link_problems(path: Path, text: str | None = None) -> list:
    """Relative links of one markdown file that name no file (or no heading)."""
    text = path.read_text() if text is None else text
    problems = []
    for target in re.findall(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", prose(text)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            if path.name == "index.md" and path.parent == DOCS and file_part in FUTURE_PAGES:
                continue
            problems.append(f"{path.name}: link {target!r}: no file {dest}")
            continue
        if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{path.name}: link {target!r}: no heading #{anchor} in {dest.name}")
    return problems


# ---------------------------------------------------------------- command lines


def clgs_lines(text: str) -> list:
    """(line number, words after ``clgs``) of every clgs command in the shell code blocks."""
    out = []
    for lang, start, lines in code_blocks(text):
        if lang not in SHELL_LANGUAGES:
            continue
        joined, first = "", None
        for offset, line in enumerate(lines):
            first = start + offset if not joined else first
            if line.rstrip().endswith("\\"):
                joined += line.rstrip()[:-1] + " "
                continue
            joined += line
            command, joined = joined.strip(), ""
            command = command[2:] if command.startswith("$ ") else command
            if not re.search(r"(^|[\s;&|])clgs(\s|$)", command):
                continue
            try:
                words = shlex.split(command, comments=True)
            except ValueError as exc:
                out.append((first, ["<unparsable>", f"{command!r}: {exc}"]))
                continue
            segment: list = []
            for word in words + [";"]:
                bare = word.rstrip(";")
                if word in SEPARATORS or word != bare:
                    if bare and word not in SEPARATORS:
                        segment.append(bare)
                    while segment and (segment[0] in SHELL_WORDS or re.match(r"^[A-Za-z_]\w*=", segment[0])):
                        segment = segment[1:]  # `do`, `then`, VAR=value before the command
                    if segment and segment[0] == "clgs":
                        out.append((first, segment[1:]))
                    segment = []
                else:
                    segment.append(word)
    return out


def _method(name: str):
    from clgs.cli.anatomy_group import _get_method

    return _get_method(name)


def _check_settings(method_names, pairs) -> None:
    """``--set KEY=VALUE`` pairs valid for one of the methods (as the commands check them)."""
    from clgs.cli.settings import check_settings, parse_settings

    errors = []
    for name in method_names:
        m, fn = _method(name)
        raw: dict = {}
        try:
            check_settings(name, m, fn, parse_settings(pairs, raw), raw)
            return
        except (click.BadParameter, click.UsageError) as exc:
            errors.append(f"{name}: {exc.format_message()}")
    raise click.UsageError("; ".join(errors))


def given(values: dict, name: str):
    """A parsed value, None when not given."""
    value = values.get(name)
    return None if value is _UNSET else value


def _convert(cmd, ctx, values: dict) -> None:
    """Each parsed value through its parameter's type (not paths: the docs' files are examples)."""
    for param in cmd.get_params(ctx):
        value = values.get(param.name, _UNSET)
        if value is None or value is _UNSET or isinstance(param.type, (click.Path, click.File)):
            continue
        flat = value if isinstance(value, (list, tuple)) else [value]
        if any(SHELL_VARIABLE in str(v) for v in flat):
            continue
        param.type_cast_value(ctx, value)


def _parse(cmd, ctx, words: list) -> tuple:
    """(values by parameter name, words left) from click's own parser for ``cmd``."""
    if hasattr(cmd, "prepare"):  # clgs reconstruct: the method's options join the command's
        cmd.prepare(ctx, list(words))
    parser = cmd.make_parser(ctx)
    values, rest, _ = parser.parse_args(list(words))
    _convert(cmd, ctx, values)
    return values, rest


def check_command(words: list) -> None:
    """Raise a click error when ``clgs WORDS`` names a command, option, value or setting that
    does not exist."""
    from clgs.anatomy import plugins
    from clgs.cli import main
    from clgs.cli.anatomy_group import default_method

    if ANATOMY_PLACEHOLDER in words:
        names = plugins.anatomy_names()
        assert names, "no anatomy installed to stand for <anatomy>"
        for name in names:
            check_command([name if w == ANATOMY_PLACEHOLDER else w for w in words])
        return
    cmd, ctx, path = main, click.Context(main, info_name="clgs", **main.context_settings), []
    words = list(words)
    while True:
        values, rest = _parse(cmd, ctx, words)
        if given(values, "help") or given(values, "show_help"):
            return
        if isinstance(cmd, click.Group):
            if not rest:
                return  # a group alone (e.g. `clgs bench`) runs its default
            name, words = rest[0], rest[1:]
            sub = cmd.get_command(ctx, name)
            if sub is None:
                raise click.UsageError(f"no command {name!r} under 'clgs {' '.join(path)}'")
            path.append(name)
            cmd, ctx = sub, click.Context(sub, info_name=name, parent=ctx, **sub.context_settings)
            continue
        break
    for param in cmd.get_params(ctx):
        if param.required and values.get(param.name, _UNSET) in (None, _UNSET):
            raise click.MissingParameter(ctx=ctx, param=param)
    anatomy = plugins.get_anatomy(path[0]) if path and path[0] in plugins.anatomy_names() else None
    settings = given(values, "settings") or []
    if rest:
        raise click.UsageError(f"unexpected extra words {rest} for 'clgs {' '.join(path)}'")
    keys = getattr(cmd.callback, "setting_keys", None)  # a command whose --set names its own options
    if path == ["reconstruct"]:
        method_names = [given(values, "method_name") or "fdk"]
    elif path == ["batch"]:
        method_names = list(given(values, "method_names") or []) or (["fdk"] if settings else [])
    elif anatomy is not None and path[1:] and path[1] in ("reconstruct", "demo"):
        method_names = [given(values, "method") or default_method(anatomy)]
    else:
        method_names = []
    if settings and keys:
        from clgs.cli.settings import options_from_settings

        options_from_settings(ctx, list(settings), keys, cmd.callback.setting_owner)
    elif settings:
        if not method_names:
            raise click.UsageError(f"--set given to 'clgs {' '.join(path)}', which runs no method")
        _check_settings(method_names, list(settings))


def command_problems(path: Path, text: str | None = None) -> list:
    text = path.read_text() if text is None else text
    problems = []
    for number, words in clgs_lines(text):
        if words[:1] == ["<unparsable>"]:
            problems.append(f"{path.name}:{number}: cannot split {words[1]}")
            continue
        try:
            check_command(words)
        except click.ClickException as exc:
            problems.append(f"{path.name}:{number}: clgs {' '.join(words)}: {exc.format_message()}")
    return problems


# ---------------------------------------------------------------- the tests


def test_the_readme_is_short():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move detail to docs/"


def test_the_docs_have_an_index_listing_every_page():
    index = (DOCS / "index.md").read_text()
    listed = set(re.findall(r"\]\(([\w.-]+\.md)\)", index))
    pages = {p.name for p in DOCS.glob("*.md")} - {"index.md"}
    assert pages <= listed, f"pages missing from docs/index.md: {sorted(pages - listed)}"


def test_every_relative_link_resolves():
    problems = [p for f in doc_files() for p in link_problems(f)]
    assert not problems, "\n".join(problems)


def test_every_clgs_command_in_the_docs_exists():
    problems = [p for f in doc_files() for p in command_problems(f)]
    assert not problems, "\n".join(problems)


def test_the_readme_has_commands_to_check():
    words = [w for _, w in clgs_lines(README.read_text())]
    assert {"simulate", "reconstruct", "evaluate", "import"} <= {w[0] for w in words}
    assert ["femur", "demo"] in [w[:2] for w in words]


@pytest.mark.parametrize("line, fault", [
    ("clgs simulate ct.nii.gz --viewz 25 --out scan", "--viewz"),
    ("clgs simulate ct.nii.gz -q --out scan", "-q"),
    ("clgs femur simulat --out scan", "simulat"),
    ("clgs reconstruct scan --method sart --iterationz 3 --out o.nii.gz", "--iterationz"),
    ("clgs reconstruct scan --method r2gs --set iterationz=3 --out run", "iterationz"),
    ("clgs femur reconstruct scan --out run --set fit_sise=off", "fit_sise"),
    ("clgs femur experiment --view-sets ap-lat carm5 --out exp", "carm5"),
    ("clgs simulate ct.nii.gz --simulation coarse --out scan", "coarse"),
    ("clgs simulate ct.nii.gz --views 25", "--out"),
    ("$ clgs bench kernels --n 50000 --dett 256", "--dett"),
    ("for p in a b; do clgs evaluate x --truth y --levell 0.02; done", "--levell"),
])
def test_the_command_check_finds_a_bad_command(line, fault):
    text = f"Text.\n\n```bash\n{line}\n```\n"
    problems = command_problems(README, text)
    assert len(problems) == 1 and fault in problems[0], problems


def test_the_command_check_passes_good_commands():
    text = ("```bash\n"
            "clgs --device pocl femur demo --iterations 5 --set log_every=5   # a comment\n"
            "clgs <anatomy> reconstruct scan --out run --set iterations=10\n"
            "clgs reconstruct scan --method sart --iterations 20 --subsets 5 --out sart.nii.gz\n"
            "clgs simulate ct.nii.gz --views 25 \\\n  --out scan25 && clgs evaluate v.nii.gz --truth scan25\n"
            "for p in fine same; do\n  clgs femur simulate --simulation $p --out f_$p\ndone\n"
            "clgs bench\n"
            "```\n")
    assert len(clgs_lines(text)) == 7
    assert command_problems(README, text) == []


def test_the_link_check_finds_a_missing_file_and_heading(tmp_path):
    text = "[a](nowhere.md) [b](results.md#no-such-heading) [c](results.md#the-papers-experiment)\n"
    problems = link_problems(DOCS / "commands.md", text)
    assert len(problems) == 2, problems
    assert "nowhere.md" in problems[0] and "no-such-heading" in problems[1]


def test_only_the_index_may_name_the_pages_still_to_come():
    text = "[o](outputs.md)\n"
    assert link_problems(DOCS / "index.md", text) == []
    assert len(link_problems(DOCS / "commands.md", text)) == (0 if (DOCS / "outputs.md").exists() else 1)


def test_the_readme_command_paths_have_help():
    seen = set()
    for _, words in clgs_lines(README.read_text()):
        path = [w for w in words[:2] if not w.startswith("-") and "." not in w and "/" not in w]
        from clgs.cli import main

        if path and isinstance(main.get_command(click.Context(main), path[0]), click.Group):
            path = path[:2]
        else:
            path = path[:1]
        if tuple(path) in seen:
            continue
        seen.add(tuple(path))
        assert "Usage:" in run(*path, "--help").output


@pytest.mark.slow
def test_the_readme_own_ct_commands_run_as_written(tmp_path, monkeypatch):
    """The own-CT block's simulation and the classical block below it, word for word, on a small CT."""
    import nibabel as nib
    import numpy as np

    blocks = [lines for lang, _, lines in code_blocks(README.read_text()) if lang in SHELL_LANGUAGES]
    own = next(b for b in blocks if any(line.startswith("clgs simulate ct.nii.gz") for line in b))
    classical = next(b for b in blocks if any("--method fdk" in line for line in b))
    commands = [w for _, w in clgs_lines("```bash\n" + "\n".join(own[:1] + classical) + "\n```\n")]
    assert [c[:1] for c in commands] == [["simulate"], ["reconstruct"], ["reconstruct"], ["evaluate"]]

    z, y, x = np.mgrid[:12, :12, :12] - 5.5
    ball = np.where(x ** 2 + y ** 2 + z ** 2 < 25, 0.02, 0.0).astype(np.float32)
    ball[4:8, 4:8, 4:8] = 0.05
    monkeypatch.chdir(tmp_path)
    nib.save(nib.Nifti1Image(ball, np.diag([4.0, 4.0, 4.0, 1.0])), "ct.nii.gz")
    outputs = [run(*words).output for words in commands]
    assert (tmp_path / "scan25" / "scan.json").exists() and (tmp_path / "fdk.nii.gz").exists()
    psnr = float(re.search(r"PSNR\s+([\d.]+)\s*dB", outputs[-1]).group(1))
    assert psnr > 15, outputs[-1]


def test_the_plugin_page_example_runs(tmp_path, monkeypatch):
    """docs/plugins.md's Python blocks run as written: a block starting ``# file: NAME.py`` is
    written to that file (an importable module), every other block is run; the plugin it defines
    is registered in-process (the method registry is restored afterwards)."""
    import sys

    from clgs.methods import registry

    for attr in ("_REGISTRY", "_LAZY", "PROVIDERS"):
        monkeypatch.setattr(registry, attr, dict(getattr(registry, attr)))
    monkeypatch.setattr(registry, "_MANAGER", [])
    monkeypatch.syspath_prepend(str(tmp_path))
    text = (DOCS / "plugins.md").read_text()
    blocks = [(start, lines) for lang, start, lines in code_blocks(text) if lang == "python"]
    assert len(blocks) >= 2
    ran = written = 0
    for start, lines in blocks:
        head = re.match(r"#\s*file:\s*(\w+\.py)\s*$", lines[0])
        if head:
            (tmp_path / head.group(1)).write_text("\n".join(lines[1:]) + "\n")
            monkeypatch.delitem(sys.modules, head.group(1)[:-3], raising=False)
            written += 1
        else:
            exec(compile("\n".join(lines), f"docs/plugins.md:{start}", "exec"), {"__name__": "docs_example"})
            ran += 1
    assert written and ran
    sys.modules.pop("clgs_knee", None)
