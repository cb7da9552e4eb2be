"""Version of the code a stage runs: a hash of its modules, so that Snakemake reruns a stage whose code
changed (no science here).

Snakemake's rerun triggers see a rule's own code, params and inputs, not the package the rule calls:
without this, a user who upgrades the pipeline keeps the old results of every stage until they delete
``results/``.  Each rule carries ``code_version(<its entry modules>)`` as a param, and the params trigger
reruns the stages whose code changed and what follows them, nothing else.

The modules are found statically (``ast``): the entry modules, every ``pipeline`` module they import
(at module level or inside a function, absolute or relative), transitively, and the packages'
``__init__``.  The hash is over their syntax trees (``ast.dump``, without line numbers): a comment, a
blank line or a re-wrapped line reruns nothing; a docstring change does (it is in the tree).  The
tree's text can change with the Python version: a new interpreter reruns everything once.
"""

from __future__ import annotations

import ast
import hashlib
from functools import cache
from pathlib import Path

PACKAGE = "pipeline"


def code_version(*modules: str, root: str | Path | None = None) -> str:
    """12 hex digits of the SHA-256 of the code of ``modules`` (dotted names, e.g.
    ``"pipeline.fits.stage"``) and of every ``pipeline`` module they import, transitively.
    ``root``: the directory holding the ``pipeline`` package (default: this one's parent)."""
    base = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for name in sorted(stage_modules(*modules, root=base)):
        h.update(name.encode() + b"\0" + _code(_module_file(name, base)) + b"\0")
    return h.hexdigest()[:12]


def stage_modules(*modules: str, root: str | Path | None = None) -> set[str]:
    """The dotted names of ``modules`` and of every ``pipeline`` module (and package) they import."""
    base = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    seen: set[str] = set()
    todo = list(modules)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _module_file(name, base)
        if path is None:
            raise ModuleNotFoundError(f"code_version: no module {name!r} under {base}")
        seen.add(name)
        parts = name.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]  # the packages' __init__ run too
        todo += [m for m in _imports(name, path) if _module_file(m, base) is not None]
    return seen


def _module_file(name: str, base: Path) -> Path | None:
    """The source file of the dotted module ``name`` under ``base`` (a module or a package), or None."""
    if name != PACKAGE and not name.startswith(PACKAGE + "."):
        return None
    p = base.joinpath(*name.split("."))
    for cand in (p.with_suffix(".py"), p / "__init__.py"):
        if cand.is_file():
            return cand
    return None


def _imports(name: str, path: Path) -> list[str]:
    """Dotted names a module imports (``from a import b`` gives a and a.b: b may be a module)."""
    return list(_parsed(path.read_bytes())[1](name, path.name == "__init__.py"))


def _code(path: Path) -> bytes:
    """The module's syntax tree as text, without line numbers: comments and layout are not in it."""
    return _parsed(path.read_bytes())[0]


@cache
def _parsed(src: bytes):
    """(syntax-tree text, function (module name, is a package) -> imported pipeline modules)."""
    tree = ast.parse(src)
    nodes = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]

    def imports(name: str, is_pkg: bool) -> tuple[str, ...]:
        here = name if is_pkg else name.rpartition(".")[0]
        out = []
        for node in nodes:
            if isinstance(node, ast.Import):
                out += [a.name for a in node.names]
                continue
            if node.level:
                up = here.split(".")
                up = up[: len(up) - (node.level - 1)]
                mod = ".".join(up + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append(mod)
            out += [f"{mod}.{a.name}" for a in node.names if a.name != "*"]
        return tuple(m for m in out if m == PACKAGE or m.startswith(PACKAGE + "."))

    return ast.dump(tree).encode(), imports
