"""The package's shape, against the layout goals of the design: small modules with one concept each.

* no import cycle inside the package (imports inside functions count; ``if TYPE_CHECKING:``
  blocks do not, they never run);
* no module over 600 lines and no function over 80 lines of code (docstring aside);
* the package no larger than the 8.2k lines it had when these goals were set, while doing more.

The module size goal is met since the single iteration engine (:mod:`torchql.engine`) replaced
the two copies of the method, and the function size goal since the problem's validation,
``profile``, ``fit_report``, ``baselines.optimize`` and ``dopri_batch`` were split into named
steps. The package size goal is not met yet; its check is a strict xfail, so that it turns into
a failure to be promoted to a plain test the day the goal is reached.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "torchql"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
MAX_PACKAGE_LINES = 8200


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(inner) for inner in ast.walk(node))
    return skip


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """``module -> modules of the package it imports`` (at any depth, outside TYPE_CHECKING blocks)."""
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        skip = _type_checking_nodes(tree)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps = set()
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for alias in node.names:
                    candidate = f"{target}.{alias.name}"
                    deps.add(candidate if candidate in modules else target)
            elif isinstance(node, ast.Import):
                deps.update(alias.name for alias in node.names)
        graph[name] = {d for d in deps if d in modules and d != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_inside_the_package():
    found = cycles(import_graph(_modules()))
    assert not found, f"import cycles: {found}"


def _long_functions() -> list[str]:
    rows = []
    for name, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                body = node.body
                if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                    body = body[1:]
                if body and body[-1].end_lineno - body[0].lineno + 1 > MAX_FUNCTION_LINES:
                    rows.append(f"{name}.{node.name}: {body[-1].end_lineno - body[0].lineno + 1} lines")
    return rows


def test_no_module_over_600_lines():
    long = {name: path.read_text().count("\n") for name, path in _modules().items()}
    assert not {k: v for k, v in long.items() if v > MAX_MODULE_LINES}


def test_no_function_over_80_lines_of_code():
    assert not _long_functions()


@pytest.mark.xfail(strict=True, reason="about 20.3k lines: one loop and one grid solver now, every built-in "
                   "propagator but torchdiffeq batched; the stiff solvers, measured inputs, estimated noise, sigma "
                   "functions, the data start, the automatic grid, DOP853, the quintic storage of h A, the "
                   "storage check and the saddle step came after the goal")
def test_package_smaller_than_when_the_goals_were_set():
    total = sum(path.read_text().count("\n") for path in _modules().values())
    assert total <= MAX_PACKAGE_LINES
