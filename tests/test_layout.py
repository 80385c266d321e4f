"""The package's layout: imports run one way through the layers, with no cycles and no private
names taken from another module, and the command line starts without torch or pyopencl.

The import graph is read from the source (every ``import`` statement, at module level or inside a
function), so a lazy import counts like any other."""
import ast
from pathlib import Path

from cli_helpers import modules_loaded_by_help

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "clgs"

# Lowest first. A module may import its own layer and the layers before it, never a later one.
LAYERS = [
    ["clgs.errors", "clgs.geometry", "clgs.progress", "clgs.commands", "clgs.install_report", "clgs.limits"],
    ["clgs.io"],
    ["clgs.mesh"],
    ["clgs.metrics", "clgs.figures"],
    ["clgs.reference"],
    ["clgs.runtime"],
    ["clgs.ops"],
    ["clgs.ct"],
    ["clgs.fit"],
    ["clgs.shape"],
    ["clgs.anatomy"],
    ["clgs.methods"],
    ["clgs.cohort", "clgs.experiment"],
    ["clgs.bench"],
    ["clgs.cli", "clgs.__main__"],
]
# The package's own __init__ is the public facade: it loads each public name from its home module
# on first attribute access.
FACADE = "clgs"
# Edges the cycle check leaves out (none: a cycle inside a subpackage is a cycle too).
ALLOWED_EDGES: set = set()


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict:
    return {module_name(p): p for p in PACKAGE.rglob("*.py")}


def imports(name: str, path: Path, known: dict):
    """(imported module, imported names) for every import statement of a module."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, []
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                yield (sub, []) if sub in known else (target, [alias.name])


def graph() -> tuple:
    known = modules()
    edges, private = {}, []
    for name, path in known.items():
        out = edges.setdefault(name, set())
        for imported, names in imports(name, path, known):
            if not imported.startswith("clgs"):
                continue
            target = imported
            while target not in known and "." in target:
                target = target.rpartition(".")[0]
            if target != name and (name, target) not in ALLOWED_EDGES:
                out.add(target)
            private += [f"{name} imports {n} from {target}" for n in names
                        if n.startswith("_") and not n.startswith("__") and target != name]
    return edges, private


def test_every_import_of_clgs_names_a_module_that_exists():
    """A module moved to another package leaves no import of its old path behind (a lazy one
    fails only when its function runs)."""
    known = modules()
    missing = [f"{name} imports {imported}" for name, path in known.items()
               for imported, _ in imports(name, path, known)
               if (imported == "clgs" or imported.startswith("clgs.")) and imported not in known]
    assert not missing, "imports of modules that do not exist:\n" + "\n".join(sorted(missing))


def layer_of(name: str) -> int:
    for i, layer in enumerate(LAYERS):
        if any(name == m or name.startswith(m + ".") for m in layer):
            return i
    raise AssertionError(f"{name} is in no layer of tests/test_layout.py: place it there")


def test_every_module_has_a_layer_and_imports_only_lower_layers():
    edges, _ = graph()
    wrong = [f"{a} (layer {layer_of(a)}) imports {b} (layer {layer_of(b)})"
             for a, targets in edges.items() if a != FACADE for b in targets
             if b != FACADE and layer_of(b) > layer_of(a)]
    assert not wrong, "imports against the layers:\n" + "\n".join(sorted(wrong))


def test_no_import_cycles():
    edges, _ = graph()
    cycles, state = [], {}

    def visit(node, stack):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node, [])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_no_import_cycles_inside_a_subpackage():
    """Within each subpackage (clgs.runtime, clgs.ops, ...) too, every import, lazy ones included,
    runs one way: each module reached from another cannot reach it back."""
    edges, _ = graph()

    def package(name):
        return name.rpartition(".")[0] if name.count(".") >= 2 else name

    def reach(start, pkg):
        seen, todo = set(), [start]
        while todo:
            for nxt in edges.get(todo.pop(), ()):
                if package(nxt) == pkg and nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    cycles = sorted(f"{a} <-> {b}" for a, targets in edges.items() for b in targets
                    if package(a) == package(b) and a < b and a in reach(b, package(a)))
    assert not cycles, "import cycles inside a subpackage:\n" + "\n".join(cycles)


def test_no_private_name_is_imported_from_another_module():
    _, private = graph()
    assert not private, "\n".join(private)


def test_the_library_below_the_cli_never_imports_click():
    edges, _ = graph()
    known = modules()
    users = [name for name, path in known.items()
             if name != FACADE and layer_of(name) < layer_of("clgs.bench")
             and any(t == "click" or t.startswith("click.") for t, _ in imports(name, path, known))]
    assert not users, "modules outside clgs.cli that import click: " + ", ".join(sorted(users))


def test_help_and_import_of_the_cli_load_neither_torch_nor_pyopencl():
    loaded = modules_loaded_by_help([["--help"]], ("torch", "pyopencl"))
    assert not loaded, f"clgs --help imported {loaded}"


CL = ROOT / "cl"


def test_kernel_sources_share_common_h_and_spell_kernel_one_way():
    """Every ``.cl`` file reaches ``common.h`` (directly or through a header it includes), none
    defines again a macro or type ``common.h`` defines, and kernels are declared ``__kernel``."""
    import re

    common = (CL / "common.h").read_text(encoding="utf-8")
    shared = set(re.findall(r"^#define (\w+)", common, re.M)) | set(re.findall(r"typedef [^;]*?(\w+);", common))
    shared -= {"CLGS_COMMON_H", "REAL"}  # the guard; REAL is the build option's default

    def includes(path):
        return re.findall(r'^#include "([^"]+)"', path.read_text(encoding="utf-8"), re.M)

    def reaches_common(path, seen=()):
        return any(inc == "common.h" or (inc not in seen and reaches_common(CL / inc, (*seen, inc)))
                   for inc in includes(path))

    problems = []
    for path in sorted(CL.glob("*.cl")) + sorted(p for p in CL.glob("*.h") if p.name != "common.h"):
        text = path.read_text(encoding="utf-8")
        if not reaches_common(path):
            problems.append(f"{path.name} does not include common.h")
        again = set(re.findall(r"^\s*#define (\w+)", text, re.M)) | set(re.findall(r"typedef [^;{]*?(\w+);", text))
        problems += [f"{path.name} defines {name} again (common.h has it)" for name in sorted(again & shared)]
        problems += [f"{path.name}:{text[:m.start()].count(chr(10)) + 1}: kernel spelled 'kernel', not '__kernel'"
                     for m in re.finditer(r"(?m)^\s*kernel\s+void\b", text)]
    assert not problems, "\n".join(problems)
