"""The shape of the code, checked so that it stays as the README describes it.

- No import cycles among the project's modules (schemas, service, worker), counting imports
  inside functions and the subcommands the CLI loads by name: an AST import graph, relative to
  packages (``import a.b`` is an edge to a.b; an edge to a package is one to its __init__), has
  no strongly connected component of more than one module.
- No module over MAX_MODULE_LINES lines and no function over MAX_FUNCTION_LINES, tests included.
- Docstrings and comments point into the repository only (the method is in docs/method.md).
- One quaternion implementation per layer: the engine's posemath and the service's plain-Python
  one; the contract only checks norms.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from import_graph import PACKAGES, import_graph, project_modules, strongly_connected

REPO = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80


def test_the_graph_sees_function_level_and_named_imports() -> None:
    graph = import_graph()
    assert "worker.align.estimator" in graph["worker.entry"]  # imported inside a function
    assert "worker.bench.cli" in graph["worker.cli"]  # the CLI's subcommand table
    assert "service.store.transitions" in graph["service.store.leases"]
    assert "schemas" in graph["worker.jobs.runner"]  # `from schemas import Camera`


def test_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert sorted(strongly_connected(graph)) == [["a", "b", "c"], ["d"]]


def test_no_import_cycles() -> None:
    cycles = [c for c in strongly_connected(import_graph()) if len(c) > 1]
    assert not cycles, f"import cycles: {cycles}"


def _python_files() -> list[Path]:
    return sorted(p for d in (*PACKAGES, "tests") for p in (REPO / d).rglob("*.py"))


def test_no_module_is_longer_than_the_limit() -> None:
    long = {
        str(p.relative_to(REPO)): n
        for p in _python_files()
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_function_is_longer_than_the_limit() -> None:
    long = {}
    for path in _python_files():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long[f"{path.relative_to(REPO)}:{node.name}"] = lines
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


@pytest.mark.parametrize("outside", ["METHOD.md", "STYLE.md"])  # in ../shared
def test_docstrings_point_into_the_repository(outside: str) -> None:
    here = Path(__file__).resolve()
    pointing = [
        str(p.relative_to(REPO)) for p in _python_files() if p != here and outside in p.read_text()
    ]
    pointing += [name for name in ("README.md", "bench/README.md", "SECURITY.md")
                 if outside in (REPO / name).read_text()]  # fmt: skip
    assert not pointing, f"{outside} is not in the repository (see docs/method.md): {pointing}"
    assert (REPO / "docs" / "method.md").is_file()


def test_one_quaternion_implementation_per_layer() -> None:
    """A module with quaternion functions is its layer's home, or builds on that home."""
    homes = {"worker": "worker.engine.posemath", "service": "service.quaternions"}
    graph = import_graph()
    others = []
    for module, path in project_modules().items():
        names = [
            node.name
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.FunctionDef) and "quaternion" in node.name
        ]
        home = homes.get(module.split(".")[0])
        if names and module != home and home not in graph[module]:
            others.append((module, names))
    assert not others, f"quaternion code outside posemath / service.quaternions: {others}"
