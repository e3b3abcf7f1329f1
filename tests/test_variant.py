"""The Mitsuba variant: 'auto' takes CUDA when Dr.Jit finds a device, and a requested CUDA
variant without one falls back to LLVM (or scalar). Each check runs in its own process, since
a process sets its variant once."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

PROBE = """
import json, sys
from worker.engine.variant import choose_variant, cuda_available
cuda = cuda_available()
chosen = choose_variant(sys.argv[1])
import mitsuba as mi
img = mi.render(mi.load_dict(mi.cornell_box()), spp=4) if sys.argv[2] == "render" else None
print(json.dumps({"cuda": cuda, "variant": chosen, "active": mi.variant(),
                  "pixels": None if img is None else int(img.shape[0] * img.shape[1])}))
"""


def _probe(requested: str, render: bool = False) -> dict[str, object]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, requested, "render" if render else "-"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


@pytest.fixture(scope="module")
def has_cuda() -> bool:
    return bool(_probe("scalar_rgb")["cuda"])


def test_auto_takes_cuda_when_there_is_a_device(has_cuda: bool) -> None:
    if not has_cuda:
        pytest.skip("no CUDA device: Dr.Jit's CUDA backend is unavailable on this machine")
    got = _probe("auto", render=True)
    assert got["variant"] == got["active"] == "cuda_ad_rgb"
    assert got["pixels"] and int(got["pixels"]) > 0  # type: ignore[call-overload]


def test_without_a_device_cuda_falls_back(has_cuda: bool) -> None:
    if has_cuda:
        pytest.skip("a CUDA device is present: there is no fallback to see")
    auto = _probe("auto")
    asked = _probe("cuda_ad_rgb")
    assert auto["variant"] == asked["variant"] == asked["active"]
    assert asked["variant"] in ("llvm_ad_rgb", "scalar_rgb")
