"""``proxpose loadtest``: many concurrent clients submit small estimates to a running service,
poll them to completion, and the figures are reported.

Each client (an asyncio task sharing one httpx connection pool) takes the next estimate of the
run, submits it (``POST /v1/estimates``, multipart, an ``Idempotency-Key`` per estimate), polls
``GET /v1/estimates/{id}`` until the job ends, then takes the next one: ``--clients`` estimates
are in flight at any time. The reference image is rendered once, up front, by the service
(``POST /v1/renders`` at the true pose: this client never loads Mitsuba); every estimate starts
from its own small perturbation of the truth and carries the truth, so the result reports the
pose error.

The clients start all at once (the first wave: every client's first submission arrives
together), or evenly over ``--ramp-s``. Reported: submit latency (accepted submissions, also
split into the first wave and the rest; throttled ones apart), status-poll latency, the same two
as the service measured them (its ``/metrics`` histogram), throughput (finished jobs per minute),
queue wait (``started_at − created_at``), run time, failures by error code, lost jobs (accepted
but not ended by the deadline), and this client's own event-loop lag and CPU use (it shares the
machine with the service, so its load shows in every latency it measures). A 429 is obeyed
(``Retry-After``) and retried with the same Idempotency-Key, as is a dropped connection. The run
is bounded: at most ``MAX_CLIENTS`` clients and ``MAX_JOBS`` jobs, ``--timeout-s`` overall
(jobs still running then are cancelled and counted as lost), and loopback URLs only. The exit
status is 0 only if every estimate was accepted and succeeded.

The package: ``config`` (the options, their defaults and bounds, the loopback guard),
``poses`` (the initial guesses), ``client`` (the asyncio clients: setup, submit, poll, cancel)
and ``report`` (the figures, the JSON report, the summary and the verdict). This module runs
them: ``add_arguments(parser)`` and ``run(args)`` are what ``proxpose loadtest`` calls.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time

from service.loadtest.client import REQUEST_TIMEOUT_S, Run
from service.loadtest.config import Config, LoadTestError, add_arguments, make_config
from service.loadtest.report import build_report, summary, verdict

__all__ = ["add_arguments", "run"]

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


async def _main(config: Config) -> tuple[Run, float, int]:
    import httpx

    headers = {"Authorization": f"Bearer {config.api_key}"} if config.api_key else {}
    limits = httpx.Limits(
        max_connections=config.clients + 4, max_keepalive_connections=config.clients + 4
    )
    async with httpx.AsyncClient(
        base_url=config.url,
        headers=headers,
        limits=limits,
        timeout=REQUEST_TIMEOUT_S,
        trust_env=False,  # never through a proxy: the target is this machine
    ) as client:
        run = Run(config, client)
        start = time.monotonic()
        await run.prepare()
        run.metrics_before = await run.scrape_metrics()
        await run.clients()
        run.metrics_after = await run.scrape_metrics()
        cancelled = await run.cancel_unfinished()
        return run, time.monotonic() - start, cancelled


def run(args: argparse.Namespace) -> int:
    """``proxpose loadtest``: 0 when every estimate succeeded and none was lost."""
    try:
        config = make_config(args)
    except LoadTestError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(
        f"proxpose loadtest: {config.clients} clients, {config.jobs} estimates of "
        f"{config.model} at {config.size} px against {config.url} (at most "
        f"{config.timeout_s:g} s)",
        flush=True,
    )
    import httpx

    try:
        loadtest, wall_s, cancelled = asyncio.run(_main(config))
    except (LoadTestError, httpx.HTTPError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    report = build_report(loadtest, wall_s, cancelled)
    problems = verdict(report, args.max_submit_p99_ms)
    report["passed"], report["problems"] = not problems, problems
    print(summary(report), flush=True)
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(report, indent=2) + "\n")
        print(f"report: {args.output}")
    for problem in problems:
        print(f"FAILED: {problem}", file=sys.stderr)
    return EXIT_OK if not problems else EXIT_FAILED
