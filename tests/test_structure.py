"""The package's shape: no import cycles (between modules, and between the stage packages), no
stage importing the synthetic-data package, and stage jobs that load only what they use."""

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"
# Imports of pipeline.synth outside it that are allowed: the CLI's make-samples (inside the command's
# function).
SYNTH_IMPORTS_ALLOWED = {("pipeline.cli", "pipeline.synth.wear_test")}


def module_names() -> dict:
    """{dotted module name: path} of every module of the package (a package by its __init__)."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imports_of(name: str, path: Path, modules: dict) -> set:
    """(imported module, at module level?) of every ``import`` of the package in one module; a
    name imported from a package is the submodule where one of that name exists."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    top_level = {id(node) for node in tree.body}
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else [])
                )
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in modules:  # `import pipeline.x.y as z`, names of a module
                target = target.rpartition(".")[0]
            if target.startswith("pipeline") and target != name:
                found.add((target, id(node) in top_level))
    return found


def import_graph() -> dict:
    modules = module_names()
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def find_cycle(edges: dict):
    """A cycle of the directed graph {node: set of nodes} as a list, or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(edges):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def stage_package(module: str) -> str:
    """pipeline.<first part>: the stage (or shared module) a module belongs to."""
    return ".".join(module.split(".")[:2])


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_no_import_cycle_between_modules():
    graph = import_graph()
    edges = {m: {t for t, _ in imported} for m, imported in graph.items()}
    assert find_cycle(edges) is None


def test_no_import_cycle_between_stage_packages():
    """pipeline.tem, pipeline.inversion, ...: a package may use another only if that one does not use
    it back (the CLI's make-samples import left out)."""
    graph = import_graph()
    edges = {}
    for module, imported in graph.items():
        for target, _ in imported:
            if (module, target) in SYNTH_IMPORTS_ALLOWED:
                continue
            a, b = stage_package(module), stage_package(target)
            if a != b:
                edges.setdefault(a, set()).add(b)
    assert find_cycle(edges) is None


def test_no_stage_imports_the_synthetic_data():
    graph = import_graph()
    found = {
        (m, t)
        for m, imported in graph.items()
        for t, _ in imported
        if t.startswith("pipeline.synth") and not m.startswith("pipeline.synth")
    }
    assert found <= SYNTH_IMPORTS_ALLOWED, sorted(found - SYNTH_IMPORTS_ALLOWED)
    assert found == SYNTH_IMPORTS_ALLOWED, (
        f"no longer imported, remove from SYNTH_IMPORTS_ALLOWED: {SYNTH_IMPORTS_ALLOWED - found}"
    )
    cli = {t for t, top in graph["pipeline.cli"] if t.startswith("pipeline.synth")}
    assert cli and not any(top for t, top in graph["pipeline.cli"] if t.startswith("pipeline.synth"))


MAX_FUNCTION_LINES = 60


def function_lengths():
    """(lines without the docstring, file, name) of every function of the package."""
    out = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                body = node.body
                if len(body) > 1 and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                    body = body[1:]
                lines = node.end_lineno - body[0].lineno + 2  # the def line and the body
                out.append((lines, path.relative_to(PACKAGE.parent).as_posix(), node.name))
    return out


def test_function_lengths_counted():
    found = {(f, n): k for k, f, n in function_lengths()}
    assert found[("pipeline/cli.py", "main")] == 11  # def, 9 body lines and a blank one inside
    assert 40 < max(found.values()) <= MAX_FUNCTION_LINES  # the longest ones are counted, near the limit


def test_no_function_over_60_lines():
    """The coordinating functions are split (complexity <= 15 is ruff's C901, run by make lint)."""
    long = sorted((k, f, n) for k, f, n in function_lengths() if k > MAX_FUNCTION_LINES)
    assert not long, long


@pytest.mark.parametrize(
    "modules, not_loaded",
    [
        (["pipeline.cli"], ["matplotlib", "scipy", "h5py"]),
        (["pipeline.forces.stage"], ["matplotlib", "pipeline.mechanics"]),
        (["pipeline.inversion.stage"], ["matplotlib", "scipy.stats", "pipeline.forces.calibration"]),
        (
            ["pipeline.adhesion_range.stage", "pipeline.adhesion_range.report"],
            ["matplotlib", "scipy.stats", "pipeline.mechanics"],
        ),
    ],
)
def test_a_stage_loads_only_what_it_uses(modules, not_loaded):
    """Importing a stage (what its job does before it works) loads no plotting library (its figure
    function imports that when it draws) and no science it does not use."""
    code = (
        f"import sys, importlib\nfor m in {modules!r}: "
        f"importlib.import_module(m)\nprint([k for k in {not_loaded!r} if k in sys.modules])"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(PACKAGE.parent)},
    )
    assert proc.returncode == 0, proc.stderr[-1500:]
    assert proc.stdout.strip() == "[]"


def test_every_function_of_the_readme_equation_index_exists():
    """The README's equation index names functions that exist (a rename must update it)."""
    import importlib
    import re

    readme = (PACKAGE.parent / "README.md").read_text()
    index = readme.split("**Equation index**", 1)[1].split("\n\n", 2)[1]
    names = re.findall(r"`(pipeline(?:\.\w+)+)`", index)
    assert len(names) >= 15
    for dotted in names:
        module, _, attr = dotted.rpartition(".")
        assert callable(getattr(importlib.import_module(module), attr)), dotted
