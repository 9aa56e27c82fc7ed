"""The package's layout rules (issue 7's measured proxies), checked on the source text.

No function longer than 80 lines (60 in `solve/`, issue 26; docstring excluded), no module
longer than 450 lines, no
import cycle between the package's modules, and no underscore-private name imported from
another module of the package.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "crank_jax"
MODULES = sorted(SRC.rglob("*.py"))
MAX_FUNCTION_LINES = 80
# The solver core, which a newcomer should follow in one sitting (issue 26).
MAX_SOLVE_FUNCTION_LINES = 60
MAX_MODULE_LINES = 450


def _name(path: Path) -> str:
    parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _package(path: Path) -> str:
    name = _name(path)
    return name if path.name == "__init__.py" else name.rsplit(".", 1)[0]


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(absolute module, imported names) for every intra-package `from ... import`."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = _package(path).split(".")
            base = base[: len(base) - (node.level - 1)]
            mod = ".".join(base + ([node.module] if node.module else []))
            out.append((mod, [a.name for a in node.names]))
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("crank_jax"):
            out.append((node.module, [a.name for a in node.names]))
    return out


def _body_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    body = fn.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        body = body[1:]
    if not body:
        return 0
    return body[-1].end_lineno - body[0].lineno + 1


def test_modules_are_short():
    long = {_name(p): n for p in MODULES
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules longer than {MAX_MODULE_LINES} lines: {long}"


def _long_functions(paths, limit: int) -> dict[str, int]:
    """`module.function -> body lines` for the functions of `paths` longer than `limit`."""
    long = {}
    for p in paths:
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = _body_lines(node)
                if n > limit:
                    long[f"{_name(p)}.{node.name}"] = n
    return long


def test_functions_are_short():
    long = _long_functions(MODULES, MAX_FUNCTION_LINES)
    assert not long, f"functions longer than {MAX_FUNCTION_LINES} lines: {long}"


def test_solver_functions_are_shorter():
    long = _long_functions(sorted((SRC / "solve").glob("*.py")), MAX_SOLVE_FUNCTION_LINES)
    assert not long, f"solve/ functions longer than {MAX_SOLVE_FUNCTION_LINES} lines: {long}"


def test_no_private_names_across_modules():
    bad = []
    modules = {_name(p) for p in MODULES}
    for p in MODULES:
        for mod, names in _imports(p):
            for n in names:
                # `from . import x` imports a submodule, whose own name may be anything.
                if f"{mod}.{n}" in modules:
                    continue
                if n.startswith("_"):
                    bad.append(f"{_name(p)} imports {mod}.{n}")
    assert not bad, bad


def test_no_import_cycles():
    modules = {_name(p): p for p in MODULES}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for m, p in modules.items():
        for mod, names in _imports(p):
            for target in [f"{mod}.{n}" for n in names] + [mod]:
                if target in modules and target != m:
                    graph[m].add(target)
                    break
    # A package's __init__ re-exporting its children is not a cycle of logic.
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                if not all(modules[x].name == "__init__.py" or x == t for x in cycle[:-1]):
                    pytest.fail("import cycle: " + " -> ".join(cycle))
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
