"""The load test's figures: percentiles, the service's own latency histogram (``/metrics``),
the JSON report, its summary table and the verdict."""

from __future__ import annotations

import math
import os
import platform
import re
import time
from dataclasses import asdict
from datetime import datetime
from typing import Any

from service.loadtest.accuracy import accuracy_summary
from service.loadtest.client import REFERENCE_SPP, JobRun, Run
from service.loadtest.poses import PERTURB_TRANS_FRAC

#: The service's own latency histogram (``/metrics``), and the routes read from it.
_HISTOGRAM_BUCKET = re.compile(
    r"^proxpose_http_request_duration_seconds_bucket\{(?P<labels>.*)\} (?P<count>\S+)$"
)
SERVER_ROUTES = {"submit": ("POST", "/v1/estimates"), "poll": ("GET", "/v1/estimates/{job_id}")}


def percentile(values: list[float], p: float) -> float:
    """The ``p``-th percentile (0–100) with linear interpolation (numpy's default)."""
    ordered = sorted(values)
    rank = (len(ordered) - 1) * p / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def stats(values: list[float], scale: float = 1.0) -> dict[str, float | int | None]:
    """n, mean, p50, p95, p99 and max of ``values`` (times ``scale``); None when empty."""
    if not values:
        return {"n": 0, "mean": None, "p50": None, "p95": None, "p99": None, "max": None}
    out: dict[str, float | int | None] = {"n": len(values)}
    out["mean"] = round(scale * sum(values) / len(values), 3)
    for p in (50, 95, 99):
        out[f"p{p}"] = round(scale * percentile(values, p), 3)
    out["max"] = round(scale * max(values), 3)
    return out


Buckets = dict[tuple[str, str], dict[float, float]]


def parse_histograms(text: str | None) -> Buckets:
    """Cumulative bucket counts of the service's HTTP latency histogram by (method, route)."""
    found: Buckets = {}
    for line in (text or "").splitlines():
        match = _HISTOGRAM_BUCKET.match(line)
        if match is None:
            continue
        labels = dict(re.findall(r'(\w+)="([^"]*)"', match["labels"]))
        le = math.inf if labels.get("le") == "+Inf" else float(labels.get("le", "nan"))
        key = (labels.get("method", ""), labels.get("route", ""))
        found.setdefault(key, {})[le] = float(match["count"])
    return found


def histogram_stats(before: dict[float, float], after: dict[float, float]) -> dict[str, Any]:
    """n, p50/p95/p99 (ms, interpolated within buckets) and the share under 50 ms of the
    requests counted between two scrapes of a cumulative histogram."""
    edges = sorted(after)
    counts = [after[e] - before.get(e, 0.0) for e in edges]
    total = counts[-1] if counts else 0.0
    out: dict[str, Any] = {"n": int(total)}
    for p in (50, 95, 99):
        value = None
        if total > 0:
            target, lower, below = total * p / 100.0, 0.0, 0.0
            for edge, count in zip(edges, counts, strict=True):
                if count >= target:
                    if math.isinf(edge):
                        value = lower  # above the last finite bucket: a lower bound
                    else:
                        share = (target - below) / (count - below) if count > below else 1.0
                        value = lower + (edge - lower) * share
                    break
                lower, below = edge, count
        out[f"p{p}"] = round(1000.0 * value, 1) if value is not None else None
    under = dict(zip(edges, counts, strict=True)).get(0.05)
    out["under_50ms_pct"] = round(100.0 * under / total, 1) if total and under is not None else None
    return out


def server_latency(run: Run) -> dict[str, Any] | None:
    """Submit and poll latency as the service measured them (``/metrics``), or None."""
    before, after = parse_histograms(run.metrics_before), parse_histograms(run.metrics_after)
    if not after:
        return None
    figures: dict[str, Any] = {
        "source": "the service's /metrics histogram between the start and the end of the "
        "clients (percentiles interpolated within its buckets; the rate limiter's 429s are "
        "counted under route 'unmatched', so not here)"
    }
    for name, key in SERVER_ROUTES.items():
        figures[name] = histogram_stats(before.get(key, {}), after.get(key, {}))
    return figures


def build_report(run: Run, wall_s: float, cancelled: int) -> dict[str, Any]:
    """The JSON report: parameters, figures, failures, lost jobs and every job."""
    jobs = run.jobs
    accepted = [j for j in jobs if j.job_id]
    ended = [j for j in accepted if j.terminal]
    ends = [j.ended_at_s for j in ended if j.ended_at_s is not None]
    span_s = max(ends) if ends else 0.0
    per_min = 60.0 * len(ended) / span_s if span_s else None
    return {
        **_setting(run, wall_s),
        "jobs": _job_counts(jobs, cancelled),
        "failures_by_code": _failures_by_code(jobs),
        "throughput_jobs_per_min": round(per_min, 2) if per_min is not None else None,
        "throughput_per_worker_per_min": round(per_min / run.workers, 2)
        if per_min is not None and run.workers
        else None,
        "accuracy": accuracy_summary(jobs),
        "throughput_span_s": round(span_s, 3),
        "latency_ms": _client_latency_ms(jobs),
        "server_latency_ms": server_latency(run),
        "throttled_429": sum(j.throttled for j in jobs),
        "submit_retries": sum(j.submit_retries for j in jobs),
        "poll_errors": sum(j.poll_errors for j in jobs),
        "client": {
            "loop_lag_ms": stats(run.loop_lag_s, 1000.0),
            "cpu_fraction": round(run.client_cpu, 3),
        },
        "queue_wait_s": stats([j.queue_wait_s for j in ended if j.queue_wait_s is not None]),
        "run_time_s": stats([j.run_time_s for j in ended if j.run_time_s is not None]),
        "end_to_end_s": stats([j.end_to_end_s for j in ended if j.end_to_end_s is not None]),
        "pose_error": {
            "rotation_deg": stats(
                [j.rotation_error_deg for j in ended if j.rotation_error_deg is not None]
            ),
            "translation": stats(
                [j.translation_error for j in ended if j.translation_error is not None]
            ),
            "converged": sum(bool(j.converged) for j in ended),
        },
        "per_job": [_job_row(j) for j in jobs],
    }


def _setting(run: Run, wall_s: float) -> dict[str, Any]:
    """What was run, where, and for how long (the report's first fields)."""
    return {
        "tool": "proxpose loadtest",
        "started": datetime.fromtimestamp(time.time() - wall_s).isoformat(timespec="seconds"),
        "config": run.config.public(),
        "requested": {
            "camera": run.base_request.get("camera"),
            "options": run.base_request.get("options"),
            "reference_spp": REFERENCE_SPP,
            "initial_guess": f"truth rotated {run.config.start_deg:g}° about a random axis, moved "
            f"{100 * PERTURB_TRANS_FRAC:g} % of the range",
        },
        "service": {"workers_at_start": run.workers},
        "machine": {
            "host": platform.node(),
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
        },
        "duration_s": round(wall_s, 3),
        "setup_s": round(run.setup_s, 3),
    }


def _job_counts(jobs: list[JobRun], cancelled: int) -> dict[str, Any]:
    """How many jobs were asked for, submitted, and how each submitted one ended."""
    accepted = [j for j in jobs if j.job_id]
    lost = [j for j in accepted if not j.terminal]
    return {
        "requested": len(jobs),
        "submitted": len(accepted),
        "not_submitted": len(jobs) - len(accepted),
        "succeeded": sum(j.status == "succeeded" for j in accepted),
        "failed": sum(j.status == "failed" for j in accepted),
        "cancelled": sum(j.status == "cancelled" for j in accepted),
        "lost": len(lost),
        "lost_ids": [j.job_id for j in lost],
        "cancelled_at_deadline": cancelled,
        "requeued": sum((j.attempts or 0) > 1 for j in accepted),
    }


def _failures_by_code(jobs: list[JobRun]) -> dict[str, int]:
    """Jobs not submitted (by why) and jobs failed or cancelled (by error code)."""
    failures: dict[str, int] = {}
    for j in jobs:
        if j.job_id is None:
            code = "not_submitted:" + (j.submit_error or "deadline").split(":")[0]
        elif j.status in ("failed", "cancelled"):
            code = f"{j.status}:{j.error_code or 'none'}"
        else:
            continue
        failures[code] = failures.get(code, 0) + 1
    return failures


def _client_latency_ms(jobs: list[JobRun]) -> dict[str, Any]:
    """Latencies the clients saw, ms: submissions (all, the first wave, the rest, throttled)
    and status polls."""
    ms = 1000.0
    accepted = [j for j in jobs if j.job_id]
    first = [j for j in accepted if j.first_of_client]
    later = [j for j in accepted if not j.first_of_client]
    return {
        "submit": stats([j.submit_latency_s for j in accepted if j.submit_latency_s], ms),
        # the first wave: every client's first submission (all at once unless --ramp-s);
        # then one per finished job
        "submit_first_wave": stats(
            [j.submit_latency_s for j in first if j.submit_latency_s is not None], ms
        ),
        "submit_after_first_wave": stats(
            [j.submit_latency_s for j in later if j.submit_latency_s is not None], ms
        ),
        "submit_throttled_429": stats([x for j in jobs for x in j.throttled_latency_s], ms),
        "poll": stats([x for j in jobs for x in j.poll_latency_s], ms),
    }


def _job_row(job: JobRun) -> dict[str, Any]:
    row = asdict(job)
    for name in ("poll_latency_s", "throttled_latency_s"):
        row[name.replace("_s", "_ms")] = [round(1000.0 * x, 2) for x in row.pop(name)]
    for name, value in row.items():
        if isinstance(value, float):
            row[name] = round(value, 4)
    return row


def summary(report: dict[str, Any]) -> str:
    """A readable table of the report's headline figures."""
    cfg, req, jobs = report["config"], report["requested"], report["jobs"]
    cam, opts = req["camera"] or {}, req["options"] or {}
    lines = [
        f"proxpose loadtest → {cfg['url']} ({report['service']['workers_at_start']} worker(s), "
        f"{report['machine']['cpus']} CPUs)",
        f"requested: {cfg['clients']} clients × {cfg['jobs']} estimates of {cfg['model']}, "
        f"{cam.get('width')}×{cam.get('height')} px, "
        + (", ".join(f"{k} {v}" for k, v in opts.items() if k != "seed") or "default options")
        + f"; {req['initial_guess']}; polls every {cfg['poll_interval_s']:g} s"
        + (f"; clients started over {cfg['ramp_s']:g} s" if cfg["ramp_s"] else ""),
        "",
        f"{'':24}{'n':>6}{'mean':>9}{'p50':>9}{'p95':>9}{'p99':>9}{'max':>9}",
    ]
    rows = [
        ("submit latency (ms)", report["latency_ms"]["submit"]),
        ("  first wave (ms)", report["latency_ms"]["submit_first_wave"]),
        ("  after it (ms)", report["latency_ms"]["submit_after_first_wave"]),
        ("  throttled 429 (ms)", report["latency_ms"]["submit_throttled_429"]),
        ("status poll (ms)", report["latency_ms"]["poll"]),
        ("client loop lag (ms)", report["client"]["loop_lag_ms"]),
        ("queue wait (s)", report["queue_wait_s"]),
        ("run time (s)", report["run_time_s"]),
        ("end to end (s)", report["end_to_end_s"]),
        ("rotation error (°)", report["pose_error"]["rotation_deg"]),
        ("translation error", report["pose_error"]["translation"]),
    ]
    for name, s in rows:
        cells = "".join(
            f"{s[k]:>9.4g}" if s[k] is not None else f"{'—':>9}"
            for k in ("mean", "p50", "p95", "p99", "max")
        )
        lines.append(f"{name:<24}{s['n']:>6}{cells}")
    server = report["server_latency_ms"]
    if server is not None:
        for name in SERVER_ROUTES:
            s = server[name]
            cells = "".join(
                f"{s[k]:>9.4g}" if s[k] is not None else f"{'—':>9}" for k in ("p50", "p95", "p99")
            )
            lines.append(
                f"{'server ' + name + ' (ms)':<24}{s['n']:>6}{'':>9}{cells}{'':>9}"
                f"  ({s['under_50ms_pct']} % < 50 ms)"
            )
    throughput = report["throughput_jobs_per_min"]
    per_worker = report["throughput_per_worker_per_min"]
    accuracy = report["accuracy"]
    lines += [
        "",
        f"jobs: {jobs['requested']} requested, {jobs['submitted']} submitted, "
        f"{jobs['succeeded']} succeeded, {jobs['failed']} failed, {jobs['cancelled']} cancelled, "
        f"{jobs['not_submitted']} not submitted, {jobs['lost']} LOST"
        + (f" ({jobs['requeued']} re-queued after a lost worker)" if jobs["requeued"] else ""),
        f"throughput: {throughput if throughput is not None else '—'} estimates/min "
        f"({per_worker if per_worker is not None else '—'} per worker) over "
        f"{report['throughput_span_s']:.1f} s; {report['throttled_429']} submissions throttled "
        f"(429), {report['submit_retries']} retried, {report['poll_errors']} poll errors",
        "failures: "
        + (", ".join(f"{k} ×{v}" for k, v in report["failures_by_code"].items()) or "none"),
        f"accuracy: {accuracy['converged']} of {accuracy['succeeded']} succeeded converged, "
        f"{accuracy['within_stated_accuracy']} within their stated accuracy (3σ of the "
        f"reported covariance; {accuracy['within_1_sigma']} within 1σ)"
        + (" — toy estimates (--quick): not checked" if report["config"]["quick"] else ""),
        f"converged: {report['pose_error']['converged']} of {jobs['succeeded']} succeeded; "
        f"wall time {report['duration_s']:.1f} s (setup {report['setup_s']:.1f} s); this "
        f"client used {100 * report['client']['cpu_fraction']:.0f} % of a CPU",
    ]
    return "\n".join(lines)


def verdict(report: dict[str, Any], max_submit_p99_ms: float | None) -> list[str]:
    """Why the run failed (empty: it passed)."""
    jobs = report["jobs"]
    problems = []
    if jobs["lost"]:
        problems.append(f"{jobs['lost']} job(s) lost (accepted, never ended)")
    if jobs["succeeded"] != jobs["requested"]:
        problems.append(f"{jobs['requested'] - jobs['succeeded']} estimate(s) did not succeed")
    accuracy = report["accuracy"]
    if not report["config"]["quick"]:  # toy estimates need not converge
        unconverged = accuracy["succeeded"] - accuracy["converged"]
        if unconverged:
            problems.append(f"{unconverged} succeeded estimate(s) did not converge")
        if accuracy["outside"]:
            problems.append(
                f"{accuracy['outside']} converged estimate(s) outside their stated accuracy"
            )
    p99 = report["latency_ms"]["submit"]["p99"]
    if max_submit_p99_ms is not None and p99 is not None and p99 > max_submit_p99_ms:
        problems.append(f"submit p99 {p99:.1f} ms > {max_submit_p99_ms:g} ms")
    return problems
