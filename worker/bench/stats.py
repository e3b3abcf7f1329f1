"""Bench statistics: success, errors, drift and σ calibration per method and group.

Conventions (also stated in bench/README.md):

- A case is a *success* when the estimate returned and is within SUCCESS_ROTATION_DEG and
  SUCCESS_TRANSLATION_PCT of the truth.
- Error statistics are over *all* cases of a group: an estimate that raised (too few features,
  ...) counts with its initial offset, the pose a user would be left with.
- Drift statistics are over the estimates started at the true pose (the robustness suite),
  the first estimator seed's. With more seeds per case (``--truth-seeds``) each case's ends,
  as rotation vectors, give its *bias* (the length of their mean: where any seed goes) and its
  *spread* (their RMS distance from that mean: the part the seed decides); both are medians
  over the cases.
- The range error is signed (> 0: the estimate is farther than the truth); its median over a
  group, from the offsets and from the truth, shows a scale bias the sizes of the errors hide.
  From the offsets it is over the estimates that returned (a failure has no signed range);
  from the truth a failure counts 0, as in the other drift columns.
- Cost statistics (iterations, renders) are over the estimates that returned; wall seconds
  are over all of them (a failure costs time too).
- Percentiles interpolate linearly (numpy's default); with few cases p90 is near the maximum.
- Ratios compare a method with the baseline row (``default`` when it was run, else the first
  method): median renders, median seconds and median errors, method ÷ baseline.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

#: Largest rotation error of a successful estimate, degrees.
SUCCESS_ROTATION_DEG = 1.0
#: Largest translation error of a successful estimate, percent of the range ‖t‖.
SUCCESS_TRANSLATION_PCT = 1.0

Record = dict[str, Any]
Stats = dict[str, Any]


def is_success(record: Record) -> bool:
    """Whether the estimate returned within the success thresholds."""
    return (
        not record["failed"]
        and record["rotation_deg"] <= SUCCESS_ROTATION_DEG
        and record["translation_pct"] <= SUCCESS_TRANSLATION_PCT
    )


def effective_errors(record: Record) -> tuple[float, float, float]:
    """(rotation deg, translation %, SPEED) after the estimate; the initial ones if it failed."""
    if record["failed"]:
        return (
            record["initial_rotation_deg"],
            record["initial_translation_pct"],
            record["initial_speed_score"],
        )
    return record["rotation_deg"], record["translation_pct"], record["speed_score"]


def _pct(values: Iterable[float], q: float) -> float | None:
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    return float(np.percentile(a, q)) if a.size else None


def _max(values: Iterable[float | None]) -> float | None:
    a = [v for v in values if v is not None]
    return float(max(a)) if a else None


def _mean(values: Iterable[float]) -> float | None:
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    return float(a.mean()) if a.size else None


def method_stats(records: list[Record]) -> Stats:
    """Accuracy and cost statistics of one group of records (one method, one band, ...).

    Estimates started from the case's initial guess give the errors, success and cost; those
    started at the true pose (``start`` "truth", the robustness suite) give the drift.
    """
    offset = [r for r in records if r.get("start", "offset") == "offset"]
    truth = [r for r in records if r.get("start") == "truth"]
    first = [r for r in truth if not r.get("seed_index")]
    return {
        **_offset_stats(offset),
        **_drift_stats(first),
        **seed_stats(truth),
        **_calibration_stats(offset),
    }


def _offset_stats(records: list[Record]) -> Stats:
    errs = np.array([effective_errors(r) for r in records], dtype=np.float64).reshape(-1, 3)
    returned = [r for r in records if not r["failed"]]
    return {
        "cases": len(records),
        "successes": sum(is_success(r) for r in records),
        "success_rate": sum(is_success(r) for r in records) / len(records) if records else None,
        "failures": len(records) - len(returned),
        "failure_codes": dict(Counter(r["error_code"] for r in records if r["failed"])),
        "converged": sum(bool(r.get("converged")) for r in returned),
        "rotation_deg_median": _pct(errs[:, 0], 50),
        "rotation_deg_p90": _pct(errs[:, 0], 90),
        "translation_pct_median": _pct(errs[:, 1], 50),
        "translation_pct_p90": _pct(errs[:, 1], 90),
        "range_error_pct_median": _pct((r.get("range_error_pct") for r in returned), 50),
        "speed_score_median": _pct(errs[:, 2], 50),
        "iterations_median": _pct((r["iterations"] for r in returned), 50),
        "renders_median": _pct((r["renders"] for r in returned), 50),
        "renders_mean": _mean(r["renders"] for r in returned),
        "seconds_median": _pct((r["seconds"] for r in records), 50),
        "seconds_mean": _mean(r["seconds"] for r in records),
        "seconds_p90": _pct((r["seconds"] for r in records), 90),
        "render_equivalents_median": _pct((r.get("render_equivalents") for r in returned), 50),
        "render_s_median": _pct((r.get("render_s") for r in records), 50),
        "peak_memory_mb_max": _max(r.get("peak_memory_mb") for r in returned),
        "memory_rise_mb_max": _max(r.get("memory_rise_mb") for r in returned),
    }


def _drift_stats(records: list[Record]) -> Stats:
    """How far estimates started at the true pose end from it (a failed one counts 0: it left
    the pose where it was; the failures are counted apart)."""
    rot = [0.0 if r["failed"] else r["rotation_deg"] for r in records]
    tr = [0.0 if r["failed"] else r["translation_pct"] for r in records]
    signed = [0.0 if r["failed"] else r.get("range_error_pct") for r in records]
    return {
        "drift_cases": len(records),
        "drift_failures": sum(bool(r["failed"]) for r in records),
        "drift_rotation_deg_median": _pct(rot, 50),
        "drift_rotation_deg_p90": _pct(rot, 90),
        "drift_translation_pct_median": _pct(tr, 50),
        "drift_translation_pct_p90": _pct(tr, 90),
        "drift_range_error_pct_median": _pct(signed, 50),
    }


def seed_stats(records: list[Record]) -> Stats:
    """Bias and spread of the ends of estimates started at the truth, per case over its
    estimator seeds (cases with at least two that returned), median over the cases."""
    ends: dict[str, list[list[float]]] = {}
    for r in records:
        if not r["failed"] and r.get("rotation_vector_deg") is not None:
            ends.setdefault(r["case_id"], []).append(r["rotation_vector_deg"])
    bias, spread, seeds = [], [], []
    for vectors in ends.values():
        if len(vectors) >= 2:
            v = np.asarray(vectors, dtype=np.float64)
            mean = v.mean(axis=0)
            bias.append(float(np.linalg.norm(mean)))
            spread.append(float(np.sqrt(np.mean(np.sum((v - mean) ** 2, axis=1)))))
            seeds.append(len(v))
    return {
        "drift_seeds": max(seeds, default=1),
        "drift_bias_deg_median": _pct(bias, 50),
        "drift_spread_deg_median": _pct(spread, 50),
    }


def _calibration_stats(records: list[Record]) -> Stats:
    """How many reported σ the actual errors are: median, and the share within 3 σ."""
    rot = [r["rotation_sigmas"] for r in records if r.get("rotation_sigmas") is not None]
    tr = [r["translation_sigmas"] for r in records if r.get("translation_sigmas") is not None]
    return {
        "rotation_sigmas_median": _pct(rot, 50),
        "rotation_within_3_sigma": float(np.mean(np.array(rot) <= 3.0)) if rot else None,
        "translation_sigmas_median": _pct(tr, 50),
        "translation_within_3_sigma": float(np.mean(np.array(tr) <= 3.0)) if tr else None,
    }


RATIO_KEYS = {
    "renders_x": "renders_median",
    "seconds_x": "seconds_median",
    "rotation_x": "rotation_deg_median",
    "translation_x": "translation_pct_median",
}


def add_ratios(rows: dict[str, Stats], baseline: str) -> None:
    """Add method ÷ baseline ratios (RATIO_KEYS) to every row of one group, in place."""
    base = rows.get(baseline)
    for stats in rows.values():
        for name, key in RATIO_KEYS.items():
            b = base.get(key) if base else None
            v = stats.get(key)
            stats[name] = v / b if v is not None and b else None


def group_summary(
    records: list[Record], methods: list[str], key: Callable[[Record], Any]
) -> list[dict[str, Any]]:
    """Per group (in first-seen order of ``key``), the stats of every method, with ratios."""
    groups: dict[Any, list[Record]] = {}
    for r in records:
        groups.setdefault(key(r), []).append(r)
    baseline = baseline_method(methods)
    out = []
    for group, members in groups.items():
        rows = {m: method_stats([r for r in members if r["method"] == m]) for m in methods}
        add_ratios(rows, baseline)
        out.append({"group": group, "baseline": baseline, "methods": rows})
    return out


def summarize(records: list[Record], methods: list[str]) -> dict[str, Any]:
    """Summary per band, per model and band, and over everything (the standard references);
    per reference class and per class group (control, tuned, held out) for the robustness suite; per
    terrain model for the terrain band."""
    from worker.bench.references import REFERENCE_CLASSES

    standard = [r for r in records if r.get("reference", "standard") == "standard"]
    classes = [r for r in records if r.get("reference", "standard") not in ("standard", "terrain")]
    terrain = [r for r in records if r.get("reference") == "terrain"]

    def kind(r: Record) -> str:
        return REFERENCE_CLASSES[r["reference"]].group

    return {
        "success_rotation_deg": SUCCESS_ROTATION_DEG,
        "success_translation_pct": SUCCESS_TRANSLATION_PCT,
        "by_band": group_summary(standard, methods, lambda r: r["band"]),
        "by_size": group_summary(records, methods, lambda r: r.get("size", "?")),
        "by_model_band": group_summary(standard, methods, lambda r: f"{r['model']} b{r['band']:g}"),
        "overall": group_summary(standard, methods, lambda r: "all"),
        "by_reference": group_summary(classes, methods, lambda r: r["reference"]),
        "by_reference_kind": group_summary(classes, methods, kind),
        "by_terrain": group_summary(terrain, methods, lambda r: r["model"]),
        "by_model_reference": group_summary(
            classes, methods, lambda r: f"{r['model']} {r['reference']}"
        ),
    }


def baseline_method(methods: list[str]) -> str:
    """The row ratios are taken against: ``default`` when it was run, else the first."""
    return "default" if "default" in methods else methods[0]
