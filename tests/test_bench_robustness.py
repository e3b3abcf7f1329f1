"""The robustness suite of ``proxpose bench`` (worker/bench/references.py): drift, its bias and
spread over estimator seeds, the class groups, and ``--robustness --quick`` end to end."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_bench import REPO, proxpose, record, rows_of, run_bench

from worker.bench.records import range_error_pct
from worker.bench.report import markdown
from worker.bench.stats import method_stats, summarize


def test_drift_and_calibration_come_from_their_own_records() -> None:
    offset = [
        {**record("default", 0.1 * k, 0.1), "start": "offset", "rotation_sigmas": float(k)}
        for k in (1, 2, 4)
    ]
    truth = [{**record("default", d, 0.01), "start": "truth"} for d in (0.02, 0.03, 0.05)]
    s = method_stats(offset + truth)
    assert s["cases"] == 3 and s["drift_cases"] == 3  # the truth starts are not cases
    assert s["rotation_deg_median"] == pytest.approx(0.2)
    assert s["drift_rotation_deg_median"] == pytest.approx(0.03)
    assert s["rotation_sigmas_median"] == pytest.approx(2.0)
    assert s["rotation_within_3_sigma"] == pytest.approx(2 / 3)


def test_drift_bias_and_spread_come_from_each_cases_seeds() -> None:
    """Ends from the truth as rotation vectors: a case whose seeds all go one way has a bias
    and no spread; one whose seeds scatter around the truth, a spread and no bias. The drift's
    own columns stay those of the first seed."""

    def end(case: str, seed: int, v: list[float]) -> dict[str, Any]:
        rot = float(np.linalg.norm(v))
        r = {**record("default", rot, 0.01), "case_id": case, "start": "truth"}
        return r | {"seed_index": seed, "rotation_vector_deg": v}

    biased = [end("a", k, [0.05, 0.0, 0.0]) for k in range(3)]
    scattered = [end("b", k, [0.0, s, 0.0]) for k, s in enumerate((0.02, -0.02))]
    s = method_stats(biased + scattered)
    assert s["drift_cases"] == 2 and s["drift_seeds"] == 3
    assert s["drift_rotation_deg_median"] == pytest.approx(0.035)  # first seeds: 0.05, 0.02
    assert s["drift_bias_deg_median"] == pytest.approx(0.025)  # 0.05 and 0
    assert s["drift_spread_deg_median"] == pytest.approx(0.01)  # 0 and 0.02
    one = method_stats([end("a", 0, [0.05, 0.0, 0.0]), end("b", 0, [0.0, 0.02, 0.0])])
    assert one["drift_seeds"] == 1 and one["drift_bias_deg_median"] is None


def test_range_error_is_signed_along_the_line_of_sight() -> None:
    t = np.array([3.0, 0.0, 4.0])  # range 5
    assert range_error_pct(t * 1.002, t) == pytest.approx(0.2)  # farther
    assert range_error_pct(t * 0.999, t) == pytest.approx(-0.1)  # nearer
    assert range_error_pct(t + np.array([0.4, 0.0, -0.3]), t) == pytest.approx(0.0)  # sideways


def test_the_drift_range_median_keeps_its_sign() -> None:
    """A scale bias (every estimate from the truth ends farther) shows as a signed median;
    the translation error's size alone would read the same for a scatter about the truth."""
    farther = [
        {**record("default", 0.02, e), "start": "truth", "range_error_pct": e}
        for e in (0.1, 0.2, 0.15)
    ]
    signs = (0.1, -0.2, -0.15)
    scattered = [{**r, "range_error_pct": e} for r, e in zip(farther, signs, strict=True)]
    assert method_stats(farther)["drift_range_error_pct_median"] == pytest.approx(0.15)
    assert method_stats(scattered)["drift_range_error_pct_median"] == pytest.approx(-0.15)
    assert method_stats(scattered)["drift_translation_pct_median"] == pytest.approx(0.15)


def test_robustness_summary_groups_by_class_and_kind() -> None:
    records = [
        {**record(m, 0.1, 0.1), "reference": ref, "start": start}
        for m in ("default", "pnp")
        for ref in ("faceted", "jpeg", "plain")  # a tuned class, a held-out one, the control
        for start in ("offset", "truth")
    ]
    summary = summarize(records, ["default", "pnp"])
    assert summary["by_band"] == []  # no standard references
    assert [g["group"] for g in summary["by_reference"]] == ["faceted", "jpeg", "plain"]
    kinds = {g["group"] for g in summary["by_reference_kind"]}
    assert kinds == {"tuned", "held out", "control"}
    config: dict[str, Any] = {"methods": ["default", "pnp"], "models": ["m"], "cases": 1}
    config |= {"sizes": [[64, 64]], "offsets": "uniform", "seed": 0}
    env: dict[str, Any] = {"command": "proxpose bench", "started_at": "now", "variant": "v"}
    env |= {"git_commit": "abc", "cpu_model": "cpu", "cpus_available": 2}
    md = markdown(summary, config, env)
    assert "#### Class `faceted`" in md and "#### All held out classes" in md
    assert "#### Class `plain`" in md and "#### All control classes" in md
    assert rows_of(md, "pnp") == 6  # three classes and three kinds


def test_bench_rejects_an_unknown_reference_class(tmp_path: Path) -> None:
    out = proxpose("bench", "--references", "faceted,cubist", "--output", str(tmp_path))
    assert out.returncode == 2
    assert "cubist" in out.stderr and "faceted" in out.stderr  # names the known ones


@pytest.mark.parametrize("args", [(), ("--robustness", "--starts", "offset")])
def test_bench_rejects_truth_seeds_without_a_start_at_the_truth(
    args: tuple[str, ...], tmp_path: Path
) -> None:
    out = proxpose("bench", *args, "--truth-seeds", "3", "--output", str(tmp_path))
    assert out.returncode == 2
    assert "--truth-seeds" in out.stderr and "truth" in out.stderr
    assert not (tmp_path / "bench.json").exists()  # nothing ran


def test_every_reference_class_renders_something_else(variant: str) -> None:
    """The classes differ from one another (the same seed: the same pose and sun), and the
    control class differs from the estimator's own render of the case only by its renderer."""
    from worker.bench.cases import bench_camera
    from worker.bench.references import AMBIENT, IRRADIANCE, REFERENCE_CLASSES, camera_response
    from worker.bench.synth import CaseSpec, make_case
    from worker.demo.satellite import demo_satellite_path
    from worker.engine.camera import PinholeCamera
    from worker.engine.meshes import load_model
    from worker.engine.renderer import LightingSpec, Renderer

    model = load_model(demo_satellite_path(REPO / "data"))
    images = {
        name: make_case(model, bench_camera(96), CaseSpec(5.0, 0.05), 11, reference=name)
        for name in REFERENCE_CLASSES
    }
    truths = {(tuple(c.R_true.ravel()), tuple(c.t_true)) for c in images.values()}
    assert len(truths) == 1  # paired across classes
    pixels = {name: c.reference.astype(np.float64) for name, c in images.items()}
    for name, img in pixels.items():
        assert img.shape == (96, 96, 3) and img.max() > 50, name  # the target is visible

    def apart(a: np.ndarray, b: np.ndarray) -> float:
        target = (a > 8) | (b > 8)  # over the target, not the black sky
        return float(np.abs(a - b)[target].mean())

    # The control (the bench's ray tracer with the estimator's physics) is left out of the
    # pairs: on a model whose file normals are flat already (the demo satellite's boxes) it
    # is the faceted class.
    names = [name for name in pixels if REFERENCE_CLASSES[name].group != "control"]
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert apart(pixels[a], pixels[b]) > 0.2, (a, b)
    # The control is another renderer's image of the estimator's own physics: not Mitsuba's
    # pixels, but nearer them than the classes made to differ most.
    case, case_class = images["plain"], REFERENCE_CLASSES["plain"]
    own = Renderer(
        model,
        PinholeCamera.from_schema(bench_camera(96)),
        LightingSpec(tuple(case.sun_true), IRRADIANCE, AMBIENT),  # type: ignore[arg-type]
        spp=64,
    ).render(case.R_true, case.t_true)
    own8 = camera_response(own, case_class, np.random.default_rng(0)).astype(np.float64)
    control = apart(pixels["plain"], own8)
    assert 0.2 < control < 0.8 * min(apart(pixels[n], own8) for n in ("defocus", "combined"))


@pytest.mark.slow
def test_quick_robustness_bench_reports_drift(tmp_path: Path) -> None:
    out = run_bench(
        tmp_path,
        *("--robustness", "--quick", "--references", "faceted,jpeg", "--methods", "default,pnp"),
        *("--truth-seeds", "2", "--save-cases", "all"),
    )
    data = json.loads((out / "bench.json").read_text())
    cases = data["cases"]
    assert len(cases) == 2 * (1 + 2) * 2  # classes × (offset + two truth seeds) × methods
    assert {(r["reference"], r["start"]) for r in cases} == {
        (ref, start) for ref in ("faceted", "jpeg") for start in ("offset", "truth")
    }
    for r in cases:
        if r["start"] == "truth":
            assert r["initial_rotation_deg"] == pytest.approx(0.0, abs=1e-6)
        if not r["failed"]:  # the error as a vector, as long as the angle
            assert np.linalg.norm(r["rotation_vector_deg"]) == pytest.approx(r["rotation_deg"])
            # the signed range error is a part of the translation error
            assert abs(r["range_error_pct"]) <= r["translation_pct"] + 1e-9
    for ref in ("faceted", "jpeg"):  # each class's two truth estimates have seeds of their own
        truth = [
            r for r in cases if (r["reference"], r["start"], r["method"]) == (ref, "truth", "pnp")
        ]
        assert sorted(r["seed_index"] for r in truth) == [0, 1]
        assert len({r["estimator_seed"] for r in truth}) == 2
    default = data["summary"]["by_reference"][0]["methods"]["default"]
    assert default["drift_cases"] == 1 and default["drift_rotation_deg_median"] is not None
    assert default["drift_seeds"] == 2 and default["drift_spread_deg_median"] is not None
    md = (out / "bench.md").read_text()
    assert "drift rot. median" in md and "#### Class `jpeg`" in md and "(2 seeds)" in md
    assert "drift range, signed" in md and default["drift_range_error_pct_median"] is not None
    saved = {p.name for p in (out / "cases" / "demo-faceted-00").iterdir()}
    names = {f"request_{m}{tag}.json" for m in ("default", "pnp") for tag in ("", "_truth")}
    assert names | {"request_default_truth_seed1.json", "reference.png"} <= saved
