"""What ``proxpose bench`` writes: the environment it ran in, DIR/bench.json, DIR/bench.md,
DIR/error_vs_offset.png (through :mod:`worker.bench.report`) and the summary on stdout.

Only the standard library is imported at module level (the CLI builds its parser from
:mod:`worker.bench.cli`, which imports this module).
"""

from __future__ import annotations

import json
import math
import os
import shlex
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from worker.bench.cases import CaseOutcome

JSON_FORMAT = "proxpose-bench/1"


def _git(*args: str) -> str | None:
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}  # never take .git/index.lock
    try:
        out = subprocess.run(
            ["git", *args], cwd=repo, env=env, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _cpu_model() -> str:
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment(variant: str) -> dict[str, Any]:
    """Where and how the bench ran: command, machine, variant, versions, commit."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    import drjit as dr

    versions: dict[str, str | None] = {}
    for pkg in ("proxpose", "numpy", "mitsuba", "drjit", "opencv-python-headless", "trimesh"):
        try:
            versions[pkg] = version(pkg)
        except PackageNotFoundError:
            versions[pkg] = None
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return {
        "command": shlex.join(["proxpose", *sys.argv[1:]]),
        "argv": sys.argv,
        "started_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "variant": variant,
        "drjit_threads": dr.thread_count(),
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_available": len(os.sched_getaffinity(0)),
        "load_average_start": list(os.getloadavg()),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "versions": versions,
        "git_commit": _git("rev-parse", "--short=12", "HEAD"),
        "git_dirty": None if dirty is None else bool(dirty),
    }


def _clean(value: Any) -> Any:
    """JSON-ready: numpy scalars to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, str):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_outputs(
    output_dir: Path,
    outcomes: list[CaseOutcome],
    config: dict[str, Any],
    env: dict[str, Any],
    status: str,
) -> dict[str, Any]:
    """Write bench.json, bench.md and error_vs_offset.png; return the summary."""
    from worker.bench.report import markdown, plot_error_vs_offset
    from worker.bench.stats import summarize

    records = [r for o in outcomes for r in o.records]
    summary = summarize(records, config["methods"])
    payload = {
        "format": JSON_FORMAT,
        "status": status,
        "config": config,
        "environment": env,
        "summary": summary,
        "warmups": [w for o in outcomes for w in o.warmups],
        "cases": records,
    }
    output_dir.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_clean(payload), indent=1, ensure_ascii=False, allow_nan=False)
    (output_dir / "bench.json").write_text(text + "\n")
    note = "" if status == "complete" else f"**Partial results: the run was {status}.**\n\n"
    (output_dir / "bench.md").write_text(note + markdown(summary, config, env))
    plot_error_vs_offset(records, config["methods"], str(output_dir / "error_vs_offset.png"))
    return summary


def print_summary(summary: dict[str, Any], output_dir: Path) -> None:
    """One line per band (or reference class) and method on stdout."""

    def num(v: float | None) -> str:
        return "—" if v is None else f"{v:.3g}"

    for group in summary["by_reference"] + summary.get("by_terrain", []):
        for method, s in group["methods"].items():
            if not s["cases"] and not s["drift_cases"]:
                continue
            print(
                f"{group['group']:<9} {method:<14} {s['successes']}/{s['cases']} ok  "
                f"rot. median {num(s['rotation_deg_median'])}°  "
                f"drift median {num(s['drift_rotation_deg_median'])}°  "
                + (
                    f"bias {num(s['drift_bias_deg_median'])}° "
                    f"spread {num(s['drift_spread_deg_median'])}°  "
                    if s.get("drift_bias_deg_median") is not None
                    else ""
                )
                + f"error/σ median {num(s['rotation_sigmas_median'])}"
            )
    for group in summary["by_band"]:
        for method, s in group["methods"].items():
            if not s["cases"]:
                continue
            print(
                f"≤{group['group']:g}°  {method:<14} {s['successes']}/{s['cases']} ok  "
                f"rot. median {s['rotation_deg_median']:.3g}°  "
                f"transl. median {s['translation_pct_median']:.3g} %  "
                f"{s['seconds_median']:.3g} s/estimate"
            )
    print(f"wrote {output_dir / 'bench.json'}, bench.md, error_vs_offset.png")
