"""Bench statistics and reports: the summary per method and band, Markdown tables, the plot.

Conventions (also stated in bench/README.md):

- A case is a *success* when the estimate returned and is within SUCCESS_ROTATION_DEG and
  SUCCESS_TRANSLATION_PCT of the truth.
- Error statistics are over *all* cases of a group: an estimate that raised (too few features,
  ...) counts with its initial offset, the pose a user would be left with.
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
#: Errors are drawn no lower than this on the log axes of the plot.
PLOT_FLOOR = 1e-4

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


def _mean(values: Iterable[float]) -> float | None:
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    return float(a.mean()) if a.size else None


def method_stats(records: list[Record]) -> Stats:
    """Accuracy and cost statistics of one group of records (one method, one band, ...)."""
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
        "speed_score_median": _pct(errs[:, 2], 50),
        "iterations_median": _pct((r["iterations"] for r in returned), 50),
        "renders_median": _pct((r["renders"] for r in returned), 50),
        "renders_mean": _mean(r["renders"] for r in returned),
        "seconds_median": _pct((r["seconds"] for r in records), 50),
        "seconds_mean": _mean(r["seconds"] for r in records),
        "seconds_p90": _pct((r["seconds"] for r in records), 90),
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
    """Summary per band, per model and band, and over everything."""
    return {
        "success_rotation_deg": SUCCESS_ROTATION_DEG,
        "success_translation_pct": SUCCESS_TRANSLATION_PCT,
        "by_band": group_summary(records, methods, lambda r: r["band"]),
        "by_model_band": group_summary(records, methods, lambda r: f"{r['model']} b{r['band']:g}"),
        "overall": group_summary(records, methods, lambda r: "all"),
    }


def _num(v: float | None, unit: str = "") -> str:
    return "—" if v is None else f"{v:.3g}{unit}"


def _ratio(v: float | None) -> str:
    return "—" if v is None else f"{v:.2g}×"


def _failures(stats: Stats) -> str:
    codes = stats["failure_codes"]
    return ", ".join(f"{n} {code}" for code, n in codes.items()) if codes else "0"


TABLE_HEADER = (
    "| method | success | rot. median | rot. p90 | transl. median | transl. p90 | SPEED median "
    "| iterations | renders | s / estimate | renders × | s × | rot. × | transl. × | failed |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
)


def table_row(method: str, s: Stats) -> str:
    """One Markdown row of :data:`TABLE_HEADER`."""
    rate = "—" if s["success_rate"] is None else f"{100 * s['success_rate']:.0f} %"
    cells = [
        f"`{method}`",
        f"{rate} ({s['successes']}/{s['cases']})",
        _num(s["rotation_deg_median"], "°"),
        _num(s["rotation_deg_p90"], "°"),
        _num(s["translation_pct_median"], " %"),
        _num(s["translation_pct_p90"], " %"),
        _num(s["speed_score_median"]),
        _num(s["iterations_median"]),
        _num(s["renders_median"]),
        _num(s["seconds_median"]),
        _ratio(s["renders_x"]),
        _ratio(s["seconds_x"]),
        _ratio(s["rotation_x"]),
        _ratio(s["translation_x"]),
        _failures(s),
    ]
    return "| " + " | ".join(cells) + " |\n"


def band_tables(summary: dict[str, Any]) -> str:
    """A Markdown table per band (and one over all bands), rows = methods."""
    parts = []
    for group in [*summary["by_band"], *summary["overall"]]:
        g = group["group"]
        title = "All bands" if g == "all" else f"Initial offset ≤ {g:g}° and ≤ {g:g} % of range"
        rows = "".join(table_row(m, s) for m, s in group["methods"].items())
        parts.append(f"### {title}\n\n{TABLE_HEADER}{rows}")
    return "\n".join(parts)


def model_table(summary: dict[str, Any]) -> str:
    """Successes and median rotation error per model and band, one column per method."""
    groups = summary["by_model_band"]
    if not groups:
        return ""
    methods = list(groups[0]["methods"])
    head = "| model, band | " + " | ".join(f"`{m}`" for m in methods) + " |\n"
    head += "|---" * (len(methods) + 1) + "|\n"
    rows = ""
    for group in groups:
        cells = [
            f"{s['successes']}/{s['cases']} · {_num(s['rotation_deg_median'], '°')}"
            for s in group["methods"].values()
        ]
        rows += f"| {group['group']} | " + " | ".join(cells) + " |\n"
    return head + rows


def baseline_method(methods: list[str]) -> str:
    """The row ratios are taken against: ``default`` when it was run, else the first."""
    return "default" if "default" in methods else methods[0]


def markdown(summary: dict[str, Any], config: dict[str, Any], env: dict[str, Any]) -> str:
    """The whole bench.md: how it was run, the tables per band and per model."""
    machine = f"{env['cpu_model']}, {env['cpus_available']} CPUs available"
    return (
        "## proxpose bench\n\n"
        f"`{env['command']}`  \n"
        f"{env['started_at']} · commit `{env['git_commit']}` · Mitsuba `{env['variant']}` · "
        f"{machine}  \n"
        f"Models {', '.join(config['models'])}; {config['cases']} case(s) per model and band; "
        f"{config['size_px']}×{config['size_px']} px; offsets `{config['offsets']}`; "
        f"seed {config['seed']}.\n\n"
        f"Success: ≤ {SUCCESS_ROTATION_DEG:g}° and ≤ {SUCCESS_TRANSLATION_PCT:g} % of range. "
        "Errors: rotation in degrees, translation in % of range, over all cases (a failed "
        "estimate counts with its initial offset). Iterations, renders and seconds: medians. "
        f"× columns: ratio to `{baseline_method(config['methods'])}` "
        "(medians).\n\n"
        f"{band_tables(summary)}\n"
        f"### Per model (successes · median rotation error)\n\n{model_table(summary)}"
    )


def plot_error_vs_offset(records: list[Record], methods: list[str], path: str) -> None:
    """Error after the estimate against the initial offset, per method (log y), as a PNG.

    Left: rotation, right: translation. A cross marks an estimate that raised, drawn at its
    initial offset; the dotted diagonal is "no improvement", the dashed line the success limit.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    panels = [
        ("initial_rotation_deg", 0, "rotation error, °", SUCCESS_ROTATION_DEG),
        ("initial_translation_pct", 1, "translation error, % of range", SUCCESS_TRANSLATION_PCT),
    ]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (x_key, col, label, limit) in zip(axes, panels, strict=True):
        for i, method in enumerate(methods):
            rs = [r for r in records if r["method"] == method]
            colour = colours[i % len(colours)]
            for failed, marker in ((False, "o"), (True, "x")):
                sel = [r for r in rs if r["failed"] == failed]
                x = [r[x_key] for r in sel]
                y = [max(effective_errors(r)[col], PLOT_FLOOR) for r in sel]
                ax.scatter(
                    x,
                    y,
                    marker=marker,
                    color=colour,
                    alpha=0.8,
                    s=24,
                    label=method if not failed else None,
                )
        hi = max((r[x_key] for r in records), default=1.0)
        diagonal = np.linspace(0.01 * hi, hi, 100)
        ax.plot(diagonal, diagonal, ":", color="grey", linewidth=1)
        ax.axhline(limit, linestyle="--", color="grey", linewidth=1)
        ax.set_yscale("log")
        ax.set_xlim(0, hi * 1.05)
        ax.set_xlabel(f"initial {label}")
        ax.set_ylabel(f"final {label}")
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(title="method (× = raised)", fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
