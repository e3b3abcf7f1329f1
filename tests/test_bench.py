"""Tests of ``proxpose bench``: the pure parts (methods, bands, seeds, statistics, Markdown) and
``proxpose bench --quick`` end to end in a subprocess."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from worker.bench.cases import (
    BenchSetupError,
    band_edges,
    case_seeds,
    draw_offset,
    parse_method,
)
from worker.bench.report import markdown
from worker.bench.stats import is_success, method_stats, summarize

REPO = Path(__file__).resolve().parents[1]
METHODS = ["default", "fast", "paper", "pnp"]
QUICK_TIMEOUT_S = 300


def proxpose(*args: str, env: dict[str, str] | None = None, timeout: float = 60) -> Any:
    """Run the console script (or ``python -m worker.cli`` when it is not installed)."""
    script = Path(sys.executable).with_name("proxpose")
    cmd = [str(script)] if script.is_file() else [sys.executable, "-m", "worker.cli"]
    return subprocess.run(
        [*cmd, *args],
        cwd=REPO,
        env={**os.environ, **(env or {})},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def run_bench(root: Path, *args: str) -> Path:
    """``proxpose bench ARGS`` writing under ``root`` (the output and the demo model's data
    directory), which must succeed; its output directory."""
    out = proxpose(
        "bench",
        *args,
        "--output",
        str(root / "out"),
        env={"PROXPOSE_DATA_DIR": str(root / "data")},
        timeout=QUICK_TIMEOUT_S,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "bench.json" in out.stdout
    return root / "out"


# -- pure parts -------------------------------------------------------------------------------
def test_parse_method_reads_overrides_as_json() -> None:
    spec = parse_method("default:n_samples=24:reuse_jacobian=false:detector=sift")
    assert spec.label == "default:n_samples=24:reuse_jacobian=false:detector=sift"
    assert spec.overrides == {"n_samples": 24, "reuse_jacobian": False, "detector": "sift"}
    opts = spec.options(seed=3).resolved()
    assert (opts.n_samples, opts.reuse_jacobian, opts.detector, opts.seed) == (24, False, "sift", 3)


def test_parse_method_keeps_the_preset_for_fields_not_overridden() -> None:
    opts = parse_method("paper:n_samples=12").options().resolved()
    assert opts.n_samples == 12
    assert opts.max_features == 4  # from the paper preset


@pytest.mark.parametrize("spec", ["nope", "default:bogus=1", "default:n_samples=1", "pnp:x"])
def test_parse_method_rejects_bad_specs(spec: str) -> None:
    with pytest.raises(BenchSetupError):
        parse_method(spec)


def test_band_edges() -> None:
    assert band_edges([3, 10, 20]) == [(0.0, 3), (3, 10), (10, 20)]
    for bad in ([], [10, 3], [0, 3], [3, 3]):
        with pytest.raises(BenchSetupError):
            band_edges(bad)


def test_offsets_are_drawn_inside_their_band() -> None:
    for seed in range(200):
        rot_deg, frac = draw_offset(3.0, 10.0, "uniform", np.random.default_rng(seed))
        assert 3.0 < rot_deg <= 10.0
        assert 0.03 < frac <= 0.10
    assert draw_offset(3.0, 10.0, "edge", np.random.default_rng(0)) == (10.0, 0.10)


def test_case_seeds_depend_only_on_their_own_case() -> None:
    assert case_seeds(0, "iss", 10, 2) == case_seeds(0, "iss", 10, 2)
    others = [case_seeds(1, "iss", 10, 2), case_seeds(0, "aura", 10, 2), case_seeds(0, "iss", 3, 2)]
    others.append(case_seeds(0, "iss", 10, 3))
    assert len({case_seeds(0, "iss", 10, 2), *others}) == 5
    assert all(0 <= s < 2**31 for s in case_seeds(0, "iss", 10, 2)[2:])


def record(method: str, rot: float | None, pct: float | None, **extra: Any) -> dict[str, Any]:
    """A synthetic per-case record (``rot=None``: the estimate raised)."""
    failed = rot is None
    return {
        "case_id": "m-b3-00",
        "model": "m",
        "band": 3.0,
        "method": method,
        "failed": failed,
        "error_code": "too_few_features" if failed else None,
        "rotation_deg": rot,
        "translation_pct": pct,
        "speed_score": None if failed else 0.01,
        "initial_rotation_deg": 2.5,
        "initial_translation_pct": 2.0,
        "initial_speed_score": 0.06,
        "iterations": None if failed else 5,
        "renders": None if failed else extra.get("renders", 10),
        "seconds": extra.get("seconds", 1.0),
        "converged": not failed,
    }


def test_success_needs_both_thresholds() -> None:
    assert is_success(record("a", 0.5, 0.5))
    assert not is_success(record("a", 1.5, 0.5))
    assert not is_success(record("a", 0.5, 1.5))
    assert not is_success(record("a", None, None))


def test_stats_count_a_failure_with_its_initial_offset() -> None:
    s = method_stats([record("a", 0.1, 0.1), record("a", 0.2, 0.3), record("a", None, None)])
    assert (s["cases"], s["successes"], s["failures"]) == (3, 2, 1)
    assert s["failure_codes"] == {"too_few_features": 1}
    assert s["rotation_deg_median"] == pytest.approx(0.2)
    assert s["rotation_deg_p90"] == pytest.approx(0.2 + 0.8 * (2.5 - 0.2))
    assert s["renders_median"] == 10  # over the estimates that returned
    assert s["seconds_mean"] == pytest.approx(1.0)


def test_summary_ratios_against_default() -> None:
    records = [
        record("default", 0.2, 0.1, renders=20, seconds=4.0),
        record("pnp", 0.4, 0.1, renders=5, seconds=1.0),
    ]
    band = summarize(records, ["default", "pnp"])["by_band"][0]
    assert band["baseline"] == "default"
    pnp = band["methods"]["pnp"]
    assert (pnp["renders_x"], pnp["seconds_x"], pnp["rotation_x"]) == (0.25, 0.25, 2.0)
    assert band["methods"]["default"]["renders_x"] == 1.0


def rows_of(md: str, method: str) -> int:
    """Table rows of ``method`` in Markdown text."""
    return sum(line.startswith(f"| `{method}` |") for line in md.splitlines())


def test_markdown_has_a_row_per_method_and_band() -> None:
    records = [record(m, 0.2, 0.1) for m in METHODS]
    records += [{**record(m, 3.0, 4.0), "band": 10.0, "case_id": "m-b10-00"} for m in METHODS]
    config: dict[str, Any] = {
        "methods": METHODS,
        "models": ["m"],
        "cases": 1,
        "sizes": [[64, 64]],
        "offsets": "uniform",
    }
    config["seed"] = 0
    env: dict[str, Any] = {"command": "proxpose bench", "started_at": "now", "variant": "v"}
    env["git_commit"] = "abc"
    env |= {"cpu_model": "cpu", "cpus_available": 2}
    md = markdown(summarize(records, METHODS), config, env)
    assert "### Initial offset ≤ 3° and ≤ 3 % of range" in md
    assert "### Initial offset ≤ 10° and ≤ 10 % of range" in md
    for m in METHODS:
        assert rows_of(md, m) == 3  # two bands and the overall table


def test_markdown_of_an_empty_run() -> None:
    config: dict[str, Any] = {
        "methods": METHODS,
        "models": [],
        "cases": 1,
        "sizes": [[64, 64]],
        "offsets": "edge",
    }
    config["seed"] = 0
    env: dict[str, Any] = {"command": "proxpose bench", "started_at": "now", "variant": "v"}
    env["git_commit"] = None
    env |= {"cpu_model": "cpu", "cpus_available": 2}
    assert "ratio to `default`" in markdown(summarize([], METHODS), config, env)


# -- the command ------------------------------------------------------------------------------
def test_bench_module_imports_nothing_heavy() -> None:
    code = (
        "import sys, worker.bench.cli; "
        "print(sorted(m for m in ('numpy', 'cv2', 'mitsuba', 'drjit') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_bench_rejects_an_unknown_method() -> None:
    out = proxpose("bench", "--methods", "default,fastest", "--output", "/nonexistent")
    assert out.returncode == 2
    assert "fastest" in out.stderr


def test_bench_skips_an_absent_shared_model(tmp_path: Path) -> None:
    args = ("bench", "--models", "iss", "--models-dir", str(tmp_path), "--output", str(tmp_path))
    out = proxpose(*args, env={"PROXPOSE_REQUIRE_SHARED": "0"})
    assert out.returncode == 2
    assert "skipping model 'iss'" in out.stderr
    out = proxpose(*args, env={"PROXPOSE_REQUIRE_SHARED": "1"})
    assert out.returncode == 2
    assert "not found" in out.stderr


def test_bench_sequences_look_for_models_in_models_dir(tmp_path: Path) -> None:
    args = ("bench", "--sequences", "approach", "--models", "iss", "--models-dir", str(tmp_path))
    out = proxpose(*args, "--output", str(tmp_path), env={"PROXPOSE_REQUIRE_SHARED": "1"})
    assert out.returncode == 2
    assert "not found" in out.stderr and str(tmp_path) in out.stderr


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``proxpose bench --quick`` once for the tests below; its output directory."""
    return run_bench(tmp_path_factory.mktemp("bench"), "--quick")


@pytest.mark.slow
def test_quick_bench_writes_complete_json(quick_run: Path) -> None:
    data = json.loads((quick_run / "bench.json").read_text())
    assert (data["format"], data["status"]) == ("proxpose-bench/1", "complete")
    assert data["config"]["methods"] == METHODS
    assert data["environment"]["variant"] in ("llvm_ad_rgb", "scalar_rgb")
    assert data["environment"]["command"].startswith("proxpose bench --quick")
    cases = data["cases"]
    assert len(cases) == 3 * len(METHODS)  # one case per band, every method on it
    for band in (3.0, 10.0, 20.0):
        ids = {r["case_id"] for r in cases if r["band"] == band}
        assert len(ids) == 1
        in_band = [r for r in cases if r["band"] == band]
        assert sorted(r["method"] for r in in_band) == METHODS
        offsets = {(r["initial_rotation_deg"], r["initial_translation_pct"]) for r in in_band}
        assert len(offsets) == 1  # paired: the same initial guess for every method
    for r in cases:
        assert r["seconds"] > 0
        assert r["error_code"] if r["failed"] else r["rotation_deg"] >= 0 and r["renders"] >= 1
    for group in data["summary"]["by_band"]:
        assert set(group["methods"]) == set(METHODS)
        assert all(s["cases"] == 1 for s in group["methods"].values())


@pytest.mark.slow
def test_quick_bench_writes_markdown_and_plot(quick_run: Path) -> None:
    md = (quick_run / "bench.md").read_text()
    for band in (3, 10, 20):
        assert f"### Initial offset ≤ {band}° and ≤ {band} % of range" in md
    for m in METHODS:
        assert rows_of(md, m) == 4  # three bands and the overall table
    png = quick_run / "error_vs_offset.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 400


# -- sizes and costs --------------------------------------------------------------------------
def test_sizes_are_squares_or_width_by_height() -> None:
    from worker.bench.cli import _sizes

    assert _sizes("512, 1920x1200") == [[512, 512], [1920, 1200]]
    with pytest.raises(Exception, match="WxH"):
        _sizes("1920by1200")


def test_a_non_square_bench_camera_has_an_off_centre_principal_point() -> None:
    from worker.bench.cases import bench_camera

    square = bench_camera(512)
    assert (square.cx, square.cy) == (255.5, 255.5)
    wide = bench_camera(640, 480)
    assert wide.fx == pytest.approx(square.fx * 480 / 512)  # the same field on the short side
    assert wide.cx > 319.5 + 10 and wide.cy < 239.5 - 5


def test_costs_are_summarised_per_size() -> None:
    records = [
        {**record("default", 0.1, 0.1), "size": size, "render_s": 0.05,
         "render_equivalents": re, "peak_memory_mb": mb, "memory_rise_mb": rise}
        for size, re, mb, rise in (("512x512", 14.0, 600.0, 80.0), ("1920x1200", 5.0, 950.0, 310.0))
    ]  # fmt: skip
    groups = {g["group"]: g["methods"]["default"] for g in summarize(records, METHODS)["by_size"]}
    assert groups["512x512"]["render_equivalents_median"] == 14.0
    assert groups["1920x1200"]["peak_memory_mb_max"] == 950.0
    assert groups["1920x1200"]["memory_rise_mb_max"] == 310.0
