"""The layout reads as the data flow: every module imports only from its own floor or below.

Floors (see /README.md, "Layout"):
1. contracts: the modules directly in ``tesseract4d/`` (errors, runtime, conventions, geometry, ...)
2. the stages of the data flow: ``datagen/``, ``tesseract4d/model/``, ``reconstruction/``
3. what reads their outputs: ``tesseract4d/evaluation/``, ``viewer/``, ``tesseract4d/policy/``
4. the command line ``tesseract4d/cli/``, the only package allowed to import everything.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("tesseract4d", "datagen", "reconstruction", "viewer")
# Longest prefix first: the floor of a module is the floor of the longest package prefix it has.
FLOORS = {
    "tesseract4d.cli": 4,
    "tesseract4d.testing": 3,
    "tesseract4d.evaluation": 3,
    "viewer": 3,
    "tesseract4d.policy": 3,
    "datagen": 2,
    "tesseract4d.model": 2,
    "tesseract4d.training": 2,
    "reconstruction": 2,
    "tesseract4d": 1,
}


def floor_of(module: str) -> int | None:
    for prefix in sorted(FLOORS, key=len, reverse=True):
        if module == prefix or module.startswith(prefix + "."):
            return FLOORS[prefix]
    return None


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(path: Path, root: Path = ROOT) -> list[tuple[int, list[str]]]:
    """Per import statement anywhere in a file (lazy imports count): its line and the absolute
    names it may import (`from tesseract4d import cli` may import the sub-package `tesseract4d.cli`)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module_name(path, root) if path.name == "__init__.py" else module_name(path, root).rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.append((node.lineno, [alias.name for alias in node.names]))
        elif isinstance(node, ast.ImportFrom):
            name = node.module or ""
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            found.append((node.lineno, [name] + [f"{name}.{alias.name}" for alias in node.names]))
    return found


def project_modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def upward_imports(path: Path, root: Path = ROOT) -> list[str]:
    """One line per import statement that reaches a floor above the module's own."""
    own = floor_of(module_name(path, root))
    bad = []
    for line, names in imports(path, root):
        # A name that is an attribute rather than a sub-module resolves to its package's floor.
        target = max((floor_of(n) or 0 for n in names if n.split(".")[0] in PACKAGES), default=0)
        if own is not None and target > own:
            bad.append(f"{path.relative_to(root)}:{line} (floor {own}) imports {names[0]} (floor {target})")
    return bad


def test_floors_cover_every_module():
    unplaced = [str(p.relative_to(ROOT)) for p in project_modules() if floor_of(module_name(p)) is None]
    assert not unplaced, f"modules on no floor: {unplaced}"


def test_no_module_imports_from_a_floor_above_it():
    violations = [v for p in project_modules() for v in upward_imports(p)]
    assert not violations, "imports that climb a floor:\n" + "\n".join(violations)


@pytest.mark.parametrize("source, expected", [
    ("from tesseract4d.cli.demo import X\n", "tesseract4d.cli.demo (floor 4)"),
    ("def f():\n    from viewer.app import ViewerApp\n", "viewer.app (floor 3)"),
    ("from tesseract4d import evaluation\n", "tesseract4d (floor 3)"),
    ("from .model import trainer\n", "tesseract4d.model (floor 2)"),
])
def test_an_upward_import_is_reported(tmp_path, source, expected):
    # A contract (floor 1) written under a temporary root: the checker must flag the climb.
    module = tmp_path / "tesseract4d" / "contract.py"
    module.parent.mkdir()
    module.write_text(source)
    found = upward_imports(module, tmp_path)
    assert len(found) == 1 and found[0].endswith(expected), found


def test_imports_from_the_same_floor_or_below_pass(tmp_path):
    module = tmp_path / "viewer" / "thing.py"
    module.parent.mkdir()
    module.write_text("import numpy\nfrom tesseract4d.errors import UserError\nfrom reconstruction.recon4d import Recon4D\n"
                      "from tesseract4d.evaluation import metrics\n")
    assert upward_imports(module, tmp_path) == []


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the project modules it imports anywhere in its file (lazy imports count): a name
    that is an attribute rather than a module resolves to the module that defines it."""
    modules = {module_name(p, root): p for pkg in PACKAGES if (root / pkg).is_dir() for p in (root / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = set()
        for _, names in imports(path, root):
            for n in names:
                while n and n not in modules:
                    n = n.rpartition(".")[0]
                if n and n != name and not name.startswith(n + "."):  # a package's own __init__ is not an edge
                    targets.add(n)
        graph[name] = targets
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_no_import_circle():
    cycles = import_cycles(import_graph())
    assert not cycles, "modules that import each other (directly or around a circle):\n" + "\n".join(
        " <-> ".join(c) for c in cycles)


def test_an_import_circle_through_a_lazy_import_is_found(tmp_path):
    (tmp_path / "datagen").mkdir()
    (tmp_path / "datagen" / "a.py").write_text("from datagen.b import B\nA = 1\n")
    (tmp_path / "datagen" / "b.py").write_text("def f():\n    from datagen.c import C\n")
    (tmp_path / "datagen" / "c.py").write_text("from datagen import a\nC = 1\n")
    (tmp_path / "datagen" / "d.py").write_text("from datagen.a import A\n")
    assert import_cycles(import_graph(tmp_path)) == [["datagen.a", "datagen.b", "datagen.c"]]


# Dependencies whose import costs seconds or pulls a native runtime: the only reason a module of the
# project may import another inside a function (outside the command line, which loads per subcommand).
HEAVY_DEPENDENCIES = {"torch", "sapien", "mani_skill", "open3d", "ray", "viser", "diffusers", "transformers",
                      "safetensors", "playwright", "gymnasium", "mplib"}


def module_files(root: Path = ROOT) -> dict[str, Path]:
    return {module_name(p, root): p for pkg in PACKAGES if (root / pkg).is_dir() for p in (root / pkg).rglob("*.py")}


def heavy_dependencies(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the heavy dependencies importing it loads (its module-level imports, followed
    through the project's modules and their packages)."""
    files = module_files(root)

    def resolve(name: str) -> str:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name

    def top_level(module: str) -> list[str]:
        names = []
        for node in ast.parse(files[module].read_text()).body:
            body = node.body + node.orelse if isinstance(node, ast.If) else node.body if isinstance(node, ast.Try) else [node]
            for stmt in body:
                if isinstance(stmt, ast.Import):
                    names += [a.name for a in stmt.names]
                elif isinstance(stmt, ast.ImportFrom) and stmt.module and not stmt.level:
                    names += [stmt.module] + [f"{stmt.module}.{a.name}" for a in stmt.names]
        parts = module.split(".")
        return names + [".".join(parts[:i]) for i in range(1, len(parts))]

    found: dict[str, set[str]] = {}

    def visit(module: str, path: tuple[str, ...] = ()) -> set[str]:
        if module in found:
            return found[module]
        out = set()
        for name in top_level(module):
            first = name.split(".")[0]
            if first in HEAVY_DEPENDENCIES:
                out.add(first)
            elif first in PACKAGES and (target := resolve(name)) and target != module and target not in path:
                out |= visit(target, path + (module,))
        if not path:
            found[module] = out
        return out

    return {m: visit(m) for m in files}


def lazy_import_problems(root: Path = ROOT) -> list[str]:
    """One line per function-local import of a project module (outside the command line) that
    defers nothing heavy, or defers without a ``# deferred: ...`` comment on it or just above it."""
    files, heavy = module_files(root), heavy_dependencies(root)
    problems = []
    for module, path in sorted(files.items()):
        if module.startswith("tesseract4d.cli"):
            continue
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        local = {id(n): n for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                 for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
        for node in sorted(local.values(), key=lambda n: n.lineno):
            if isinstance(node, ast.ImportFrom):
                names = [] if node.level or not node.module else [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                names = [a.name for a in node.names]
            targets = set()
            for name in names:
                if name.split(".")[0] in PACKAGES:
                    while name and name not in files:
                        name = name.rpartition(".")[0]
                    targets.add(name)
            targets.discard("")
            if not targets:
                continue
            deferred = set().union(*(heavy[t] for t in targets)) - heavy[module]
            where = f"{path.relative_to(root)}:{node.lineno}"
            if not deferred:
                problems.append(f"{where} imports {sorted(targets)[0]} inside a function but defers nothing heavy: "
                                f"import it at the top of the module")
                continue
            above = node.lineno - 2  # index of the line above; step over the imports of the same group
            while above >= 0 and lines[above].strip().startswith(("from ", "import ")):
                above -= 1
            if "# deferred" not in lines[node.lineno - 1] and not (above >= 0 and lines[above].strip().startswith("# deferred")):
                problems.append(f"{where} defers {', '.join(sorted(deferred))} without saying so (# deferred: ...)")
    return problems


def test_a_lazy_project_import_defers_a_heavy_dependency_and_says_so():
    problems = lazy_import_problems()
    assert not problems, "\n".join(problems)


def test_a_lazy_import_that_defers_nothing_or_says_nothing_is_reported(tmp_path):
    (tmp_path / "datagen").mkdir()
    (tmp_path / "datagen" / "light.py").write_text("X = 1\n")
    (tmp_path / "datagen" / "heavy.py").write_text("import torch\nY = 1\n")
    (tmp_path / "datagen" / "user.py").write_text(
        "def a():\n    from datagen.light import X\n    return X\n\n\n"
        "def b():\n    from datagen.heavy import Y\n    return Y\n\n\n"
        "def c():\n    # deferred: imports torch\n    from datagen.heavy import Y\n    return Y\n")
    problems = lazy_import_problems(tmp_path)
    assert len(problems) == 2, problems
    assert "user.py:2" in problems[0] and "defers nothing heavy" in problems[0]
    assert "user.py:7" in problems[1] and "without saying so" in problems[1]
