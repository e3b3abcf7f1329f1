"""Bench reports: Markdown tables per band, per model and per reference class, and the plot
of error against initial offset (statistics in :mod:`worker.bench.stats`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from worker.bench.stats import (
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_PCT,
    Record,
    Stats,
    baseline_method,
    effective_errors,
)

#: Errors are drawn no lower than this on the log axes of the plot.
PLOT_FLOOR = 1e-4


def _num(v: float | None, unit: str = "") -> str:
    return "—" if v is None else f"{v:.3g}{unit}"


def _signed(v: float | None, unit: str = "") -> str:
    return "—" if v is None else f"{v:+.3g}{unit}"


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


def _fill_text(config: dict[str, Any]) -> str:
    """The spacecraft cases' size when not the default (older bench.json files have none)."""
    from worker.bench.synth import CaseSpec

    default = CaseSpec(0.0, 0.0).fill
    fill = config.get("fill", default)
    if fill == default:
        return ""
    past = " (past the frame)" if fill > 1 else ""
    return f"spacecraft {fill:g} × the image side across{past}; "


def markdown(summary: dict[str, Any], config: dict[str, Any], env: dict[str, Any]) -> str:
    """The whole bench.md: how it was run, the tables per band and per model, and the
    robustness tables per reference class when the suite had any."""
    machine = f"{env['cpu_model']}, {env['cpus_available']} CPUs available"
    parts = [
        "## proxpose bench\n\n"
        f"`{env['command']}`  \n"
        f"{env['started_at']} · commit `{env['git_commit']}` · Mitsuba `{env['variant']}` · "
        f"{machine}  \n"
        f"Models {', '.join(config['models'])}; {config['cases']} case(s) per model and "
        f"{'class' if summary['by_reference'] else 'band'}; "
        f"{', '.join(f'{w}×{h}' for w, h in config['sizes'])} px; offsets `{config['offsets']}`; "
        f"{_fill_text(config)}seed {config['seed']}.\n\n"
        f"Success: ≤ {SUCCESS_ROTATION_DEG:g}° and ≤ {SUCCESS_TRANSLATION_PCT:g} % of range. "
        "Errors: rotation in degrees, translation in % of range, over all cases (a failed "
        "estimate counts with its initial offset). Iterations, renders and seconds: medians. "
        f"× columns: ratio to `{baseline_method(config['methods'])}` (medians).\n\n"
    ]
    if summary["by_band"]:
        parts.append(
            f"{band_tables(summary)}\n"
            f"### Per model (successes · median rotation error)\n\n{model_table(summary)}"
        )
    if summary["by_reference"]:
        parts.append(robustness_tables(summary))
    if summary.get("by_terrain"):
        parts.append(terrain_tables(summary, config))
    parts.append(size_table(summary))
    return "".join(parts)


SIZE_HEADER = (
    "| size | method | success | rot. median | transl. median | renders | s / estimate "
    "| full render, s | render-equivalents | peak memory, MiB | memory rise, MiB |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|\n"
)


def size_table(summary: dict[str, Any]) -> str:
    """Cost per image size and method: seconds, renders, render-equivalents (engine seconds ÷
    one full-resolution render of the same case, timed in the same run), peak memory."""
    rows = ""
    for group in summary["by_size"]:
        for method, s in group["methods"].items():
            rate = "—" if s["success_rate"] is None else f"{100 * s['success_rate']:.0f} %"
            cells = [
                str(group["group"]).replace("x", "×"),
                f"`{method}`",
                f"{rate} ({s['successes']}/{s['cases']})",
                _num(s["rotation_deg_median"], "°"),
                _num(s["translation_pct_median"], " %"),
                _num(s["renders_median"]),
                _num(s["seconds_median"]),
                _num(s["render_s_median"]),
                _num(s["render_equivalents_median"]),
                _num(s["peak_memory_mb_max"]),
                _num(s.get("memory_rise_mb_max")),
            ]
            rows += "| " + " | ".join(cells) + " |\n"
    if not rows:
        return ""
    return (
        "\n### Cost by image size\n\nRender-equivalents: engine seconds ÷ the time of one "
        "full-resolution render of the same case (main spp), measured in the same run; "
        "medians. Peak memory: the process's resident high-water mark, the largest; memory "
        "rise: that mark less the resident memory when the estimate started (what the "
        f"estimate itself added), the largest.\n\n"
        f"{SIZE_HEADER}{rows}"
    )


ROBUST_HEADER = (
    "| method | success | rot. median | rot. p90 | transl. median | transl. p90 "
    "| drift rot. median | drift rot. p90 | drift transl. median | drift range, signed "
    "| drift bias / spread | error/σ median | ≤ 3σ | s / estimate | rot. × |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
)


def robust_row(method: str, s: Stats) -> str:
    """One Markdown row of :data:`ROBUST_HEADER`."""
    rate = "—" if s["success_rate"] is None else f"{100 * s['success_rate']:.0f} %"
    within = s["rotation_within_3_sigma"]
    cells = [
        f"`{method}`",
        f"{rate} ({s['successes']}/{s['cases']})",
        _num(s["rotation_deg_median"], "°"),
        _num(s["rotation_deg_p90"], "°"),
        _num(s["translation_pct_median"], " %"),
        _num(s["translation_pct_p90"], " %"),
        _num(s["drift_rotation_deg_median"], "°"),
        _num(s["drift_rotation_deg_p90"], "°"),
        _num(s["drift_translation_pct_median"], " %"),
        _signed(s.get("drift_range_error_pct_median"), " %"),
        _bias_spread(s),
        _num(s["rotation_sigmas_median"]),
        "—" if within is None else f"{100 * within:.0f} %",
        _num(s["seconds_median"]),
        _ratio(s["rotation_x"]),
    ]
    return "| " + " | ".join(cells) + " |\n"


def _bias_spread(s: Stats) -> str:
    """The drift's bias and spread over the estimator seeds (— with one seed per case)."""
    if s.get("drift_bias_deg_median") is None:
        return "—"
    bias, spread = _num(s["drift_bias_deg_median"], "°"), _num(s["drift_spread_deg_median"], "°")
    return f"{bias} / {spread} ({s['drift_seeds']} seeds)"


def terrain_tables(summary: dict[str, Any], config: dict[str, Any]) -> str:
    """A table per terrain model (the tuned generator, the held-out one), rows = methods."""
    from worker.bench.config import TERRAIN_BAND
    from worker.bench.terrain import TERRAIN_MODELS, TERRAIN_REFERENCE

    lo, hi = TERRAIN_BAND
    sun_lo, sun_hi = config["sun_elevation_deg"]
    alt_lo, alt_hi = config["altitude_m"]
    tilt_lo, tilt_hi = config["tilt_deg"]
    parts = [
        "\n### Terrain band: a cratered heightfield filling the frame\n\n"
        f"Camera {alt_lo:g}–{alt_hi:g} m above the ground, tilted {tilt_lo:g}–{tilt_hi:g}° from "
        "the nadir; sun "
        f"{sun_lo:g}–{sun_hi:g}° above the horizon; offsets in ({lo:g}, {hi:g}]° and % of range; "
        f"references: {TERRAIN_REFERENCE.description}. Each estimate "
        "also runs from the true pose (drift). `terrain` is the generator the estimator was "
        "tuned on; `terrain-ridged` (ridged relief) was held out.\n"
    ]
    for group in summary["by_terrain"]:
        name = group["group"]
        rows = "".join(robust_row(m, s) for m, s in group["methods"].items())
        parts.append(f"\n#### `{name}`: {TERRAIN_MODELS.get(name, name)}\n\n{ROBUST_HEADER}{rows}")
    return "".join(parts)


def robustness_tables(summary: dict[str, Any]) -> str:
    """A table per class group (control, tuned, held out) and per reference class, rows =
    methods."""
    from worker.bench.references import REFERENCE_CLASSES

    parts = [
        "### Robustness: references made with other physics\n\n"
        "Every estimate runs twice: from the case's initial guess (the error columns) and from "
        "the true pose (drift: how far it walks away from the truth). With `--truth-seeds N` "
        "each case runs N times from the truth with other estimator seeds: bias is the length "
        "of the mean of their rotation errors (as vectors), spread their RMS distance from it "
        "(what the seed decides), medians over the cases. Drift range, signed: the median "
        "error along the line of sight from the truth, % of the range (> 0: farther than "
        "the truth), a scale bias when it holds its sign. error/σ: the "
        "rotation error over the reported 1-σ (RMS over the axes); ≤ 3σ: the share of errors "
        "within three of them. *Tuned* classes were looked at while developing the estimator; "
        "*held out* ones were not; the *control* class (`plain`) differs from the estimator's "
        "renders only by its renderer.\n"
    ]
    for group in summary["by_reference_kind"] + summary["by_reference"]:
        name = group["group"]
        cls = REFERENCE_CLASSES.get(name)
        title = f"Class `{name}`: {cls.description}" if cls else f"All {name} classes"
        rows = "".join(robust_row(m, s) for m, s in group["methods"].items())
        parts.append(f"\n#### {title}\n\n{ROBUST_HEADER}{rows}")
    return "".join(parts)


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
