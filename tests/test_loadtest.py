"""``proxpose loadtest``: the CI smoke test (``--quick`` against ``proxpose serve`` with an
embedded Redis and two workers, started here on free ports), and its parts without a service
(the loopback guard, the bounds, the percentiles, the initial guesses)."""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import REPO, free_port

from service import loadtest
from service.loadtest.config import (
    QUICK,
    QUICK_OPTIONS,
    LoadTestError,
    check_loopback,
    make_config,
)
from service.loadtest.poses import PERTURB_ROT_DEG, PERTURB_TRANS_FRAC, perturbed_pose
from service.loadtest.report import histogram_stats, parse_histograms, percentile, stats

#: How long `proxpose serve` may take to have both workers registered, s.
READY_TIMEOUT_S = 120.0
#: Bound of the quick load test itself, s (it passes --timeout-s below this).
QUICK_TIMEOUT_S = 150.0


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    loadtest.add_arguments(parser)
    return parser.parse_args(list(argv))


# ----------------------------------------------------------------------------- without a service
@pytest.mark.parametrize(
    "url", ["http://10.0.0.1:8000", "http://example.com", "https://8.8.8.8/", "ftp://127.0.0.1"]
)
def test_only_loopback_urls_are_accepted(url: str) -> None:
    with pytest.raises(LoadTestError):
        check_loopback(url)


@pytest.mark.parametrize(
    "url",
    ["http://127.0.0.1:8000/", "http://localhost:1234", "http://[::1]:80", "http://127.9.9.9"],
)
def test_loopback_urls_pass(url: str) -> None:
    assert check_loopback(url) == url.rstrip("/")


def test_cli_refuses_a_remote_url_with_a_clear_error() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "worker.cli", "loadtest", "--url", "http://192.0.2.7:8000"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "only targets a service on this machine" in out.stderr


def test_quick_defaults_and_bounds() -> None:
    quick = make_config(parse("--quick"))
    assert (quick.clients, quick.jobs, quick.size) == (4, 8, QUICK["size"])
    full = make_config(parse())
    assert (full.clients, full.jobs) == (50, 200)
    assert make_config(parse("--quick", "--jobs", "3")).jobs == 3  # explicit wins
    for bad in (["--clients", "0"], ["--jobs", "100000"], ["--timeout-s", "99999"]):
        with pytest.raises(LoadTestError):
            make_config(parse(*bad))


def test_percentiles_interpolate_like_numpy() -> None:
    values = [float(x) for x in range(1, 101)]
    assert percentile(values, 50) == pytest.approx(50.5)
    assert percentile(values, 99) == pytest.approx(99.01)
    assert percentile([3.0], 95) == 3.0
    assert stats([])["p99"] is None


def test_server_latency_from_the_metrics_histogram() -> None:
    def scrape(counts: list[float]) -> str:
        edges = ["0.005", "0.01", "0.025", "0.05", "0.1", "+Inf"]
        labels = 'method="GET",route="/v1/estimates/{job_id}"'
        return "\n".join(
            f'proxpose_http_request_duration_seconds_bucket{{le="{e}",{labels}}} {c}'
            for e, c in zip(edges, counts, strict=True)
        )

    before = parse_histograms(scrape([1, 1, 1, 1, 1, 1]))
    after = parse_histograms(scrape([1, 41, 81, 91, 100, 101]))
    key = ("GET", "/v1/estimates/{job_id}")
    figures = histogram_stats(before[key], after[key])
    assert figures["n"] == 100 and figures["under_50ms_pct"] == 90.0
    assert figures["p50"] == pytest.approx(10.0 + 15.0 * 10 / 40, abs=0.1)  # within (10, 25]
    assert figures["p99"] == 100.0  # the 99th of 100 is the last in (50, 100] ms
    assert histogram_stats({}, {})["p50"] is None


def test_initial_guesses_are_near_the_truth() -> None:
    truth = {"t": [0.3, -0.2, 14.0], "quaternion": [0.5735764, 0.6802687, 0.4081612, 0.2040806]}
    guesses = [perturbed_pose(truth, seed) for seed in range(20)]
    assert guesses[3] == perturbed_pose(truth, 3)  # deterministic
    assert len({json.dumps(g) for g in guesses}) == 20
    for guess in guesses:
        dot = abs(sum(a * b for a, b in zip(guess["quaternion"], truth["quaternion"], strict=True)))
        angle = math.degrees(2.0 * math.acos(min(1.0, dot)))
        assert angle == pytest.approx(PERTURB_ROT_DEG, abs=1e-3)
        shift = math.dist(guess["t"], truth["t"])
        assert shift == pytest.approx(PERTURB_TRANS_FRAC * math.hypot(*truth["t"]), 1e-3)


# ----------------------------------------------------------------------------- against a service
@pytest.mark.slow
def test_quick_load_test_against_proxpose_serve(tmp_path: Path) -> None:
    data_dir, log = tmp_path / "data", tmp_path / "serve.log"
    demo = REPO / "data" / "models" / "demo-sat-v1.glb"
    if demo.is_file():  # saves the workers generating it
        (data_dir / "models").mkdir(parents=True)
        shutil.copy(demo, data_dir / "models" / demo.name)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("PROXPOSE_")}
    env |= {
        "PROXPOSE_PORT": str(port),
        "PROXPOSE_EMBEDDED_REDIS_PORT": str(free_port()),
        "PROXPOSE_DATA_DIR": str(data_dir),
        "PROXPOSE_SHUTDOWN_GRACE_S": "2",
    }
    url = f"http://127.0.0.1:{port}"
    with open(log, "ab") as out:
        serve = subprocess.Popen(
            [sys.executable, "-m", "worker.cli", "serve", "--workers", "2", "--no-warmup"],
            env=env,
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while True:
            assert serve.poll() is None, log.read_text()
            assert time.monotonic() < deadline, log.read_text()
            try:
                if httpx.get(f"{url}/readyz", timeout=2.0).json().get("workers", 0) >= 2:
                    break
            except (httpx.TransportError, ValueError):
                pass
            time.sleep(0.25)
        report_path = tmp_path / "report.json"
        started = time.monotonic()
        run = subprocess.run(
            [
                *(sys.executable, "-m", "worker.cli", "loadtest", "--quick", "--url", url),
                *("--output", str(report_path), "--timeout-s", str(QUICK_TIMEOUT_S - 30)),
            ],
            cwd=REPO,
            env={k: v for k, v in env.items() if k != "PROXPOSE_API_KEY"},
            capture_output=True,
            text=True,
            timeout=QUICK_TIMEOUT_S,
        )
        elapsed = time.monotonic() - started
    finally:
        serve.send_signal(signal.SIGINT)
        try:
            serve.wait(timeout=60)
        except subprocess.TimeoutExpired:
            serve.kill()
            serve.wait()
    assert run.returncode == 0, f"{run.stdout}\n{run.stderr}\n{log.read_text()[-4000:]}"
    assert "LOST" in run.stdout and "submit latency" in run.stdout  # the summary table
    report = json.loads(report_path.read_text())
    jobs = report["jobs"]
    assert jobs["requested"] == jobs["submitted"] == jobs["succeeded"] == 8
    assert jobs["lost"] == 0 and jobs["lost_ids"] == [] and report["failures_by_code"] == {}
    assert report["passed"] is True and report["problems"] == []
    submit, poll = report["latency_ms"]["submit"], report["latency_ms"]["poll"]
    assert submit["n"] == 8 and 0 < submit["p50"] <= submit["p95"] <= submit["p99"]
    assert poll["n"] >= 8 and poll["p99"] is not None
    assert report["throughput_jobs_per_min"] > 0
    server = report["server_latency_ms"]
    assert server["submit"]["n"] == 8 and server["poll"]["n"] >= 8
    first, later = (
        report["latency_ms"][k]["n"] for k in ("submit_first_wave", "submit_after_first_wave")
    )
    assert (first, later) == (4, 4)
    assert report["queue_wait_s"]["n"] == 8 and report["queue_wait_s"]["p50"] >= 0
    assert report["requested"]["options"]["perturbation_spp"] == 1
    assert report["service"]["workers_at_start"] == 2
    assert all(row["rotation_error_deg"] is not None for row in report["per_job"])
    print(f"quick load test: {elapsed:.1f} s")


def test_accuracy_is_checked_against_the_reported_covariance() -> None:
    from types import SimpleNamespace

    from service.loadtest.accuracy import accuracy_summary, rss, within_accuracy

    def job(rot: float, trans: float, converged: bool = True, sigma: bool = True) -> Any:
        return SimpleNamespace(
            status="succeeded",
            converged=converged,
            rotation_error_deg=rot,
            translation_error=trans,
            sigma_rotation_deg=rss([0.02, 0.02, 0.01]) if sigma else None,  # 0.03°
            sigma_translation=rss([0.001, 0.002, 0.002]) if sigma else None,  # 0.003
        )

    assert rss([0.02, 0.02, 0.01]) == pytest.approx(0.03) and rss([]) is None
    assert within_accuracy(job(0.089, 0.0089))  # just inside 3σ
    assert not within_accuracy(job(0.091, 0.001))  # rotation outside
    assert not within_accuracy(job(0.01, 0.0091))  # translation outside
    assert not within_accuracy(job(0.0, 0.0, sigma=False))  # no covariance: cannot pass
    figures = accuracy_summary(
        [job(0.02, 0.002), job(0.05, 0.005), job(0.2, 0.001), job(1, 1, False)]
    )
    assert (figures["succeeded"], figures["converged"]) == (4, 3)
    assert (figures["within_stated_accuracy"], figures["within_1_sigma"], figures["outside"]) == (
        2,
        1,
        1,
    )


def test_a_full_run_sends_default_options_and_quick_the_toy_ones() -> None:
    full, quick = make_config(parse()), make_config(parse("--quick"))
    assert full.size == 256 and full.options == {} and full.start_deg == 3.0
    assert quick.options == QUICK_OPTIONS and quick.start_deg == 2.0
    assert make_config(parse("--max-iterations", "7")).options == {"max_iterations": 7}
    with pytest.raises(LoadTestError):
        make_config(parse("--start-deg", "90"))
