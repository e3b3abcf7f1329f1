"""``proxpose loadtest`` options: the command-line arguments, their defaults and bounds, the
loopback guard, and one run's :class:`Config`."""

from __future__ import annotations

import argparse
import ipaddress
import os
import socket
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

#: Bounds of a run: clients, estimates, overall seconds.
MAX_CLIENTS = 256
MAX_JOBS = 10_000
MAX_TIMEOUT_S = 3600.0
#: Defaults of a full run (real estimates: the service's default options, a start a few
#: degrees off) and of ``--quick`` (the CI smoke test: toy estimates that need not converge).
FULL = {"clients": 50, "jobs": 200, "size": 256, "timeout_s": 3600.0, "start_deg": 3.0}
QUICK = {"clients": 4, "jobs": 8, "size": 80, "timeout_s": 150.0, "start_deg": 2.0}
#: Estimate options of ``--quick``: small and quick (a full run sends none: the defaults).
QUICK_OPTIONS = {"max_iterations": 3, "spp": 4, "perturbation_spp": 1}


class LoadTestError(Exception):
    """The run cannot start (bad URL, service not ready, reference render failed)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``proxpose loadtest`` options."""
    parser.add_argument(
        "--url", default="http://127.0.0.1:8000", help="service root (loopback only)"
    )
    parser.add_argument(
        "--clients", type=int, help=f"concurrent clients (default {FULL['clients']})"
    )
    parser.add_argument("--jobs", type=int, help=f"estimates in all (default {FULL['jobs']})")
    parser.add_argument("--size", type=int, help=f"camera side, px (default {FULL['size']})")
    parser.add_argument(
        "--timeout-s", type=float, help=f"overall bound, s (default {FULL['timeout_s']:g})"
    )
    parser.add_argument("--model", default="demo-sat", help="registered model (default demo-sat)")
    parser.add_argument(
        "--max-iterations",
        type=int,
        help="iteration cap per estimate (default: the service's; "
        f"{QUICK_OPTIONS['max_iterations']} with --quick)",
    )
    parser.add_argument(
        "--start-deg",
        type=float,
        help="initial guesses: the truth rotated this far about a random axis (default "
        f"{FULL['start_deg']:g}; {QUICK['start_deg']:g} with --quick)",
    )
    parser.add_argument(
        "--poll-interval-s", type=float, default=0.5, help="status poll interval (default 0.5)"
    )
    parser.add_argument(
        "--ramp-s",
        type=float,
        default=0.0,
        help="start the clients evenly over this many seconds (default 0: all at once)",
    )
    parser.add_argument(
        "--api-key", help="Bearer key (default $PROXPOSE_API_KEY; none for an open service)"
    )
    parser.add_argument("--output", type=Path, help="write the JSON report here")
    parser.add_argument(
        "--max-submit-p99-ms",
        type=float,
        help="also fail when the submit latency's p99 is above this (default: report only)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke test: {QUICK['clients']} clients, {QUICK['jobs']} toy estimates "
        f"({QUICK_OPTIONS['max_iterations']} iterations at spp {QUICK_OPTIONS['spp']}, not "
        f"checked for accuracy), {QUICK['size']} px, {QUICK['timeout_s']:g} s (explicit "
        "options still win)",
    )


@dataclass(frozen=True)
class Config:
    """One run's parameters (after defaults and bounds)."""

    url: str
    clients: int
    jobs: int
    size: int
    timeout_s: float
    model: str
    max_iterations: int | None
    start_deg: float
    poll_interval_s: float
    ramp_s: float
    api_key: str | None
    quick: bool

    @property
    def options(self) -> dict[str, Any]:
        """The estimate options sent (a full run: the service's defaults but for an explicit
        --max-iterations; --quick: the toy options)."""
        options: dict[str, Any] = dict(QUICK_OPTIONS) if self.quick else {}
        if self.max_iterations is not None:
            options["max_iterations"] = self.max_iterations
        return options

    def public(self) -> dict[str, Any]:
        """The parameters for the report (the key left out)."""
        data = asdict(self)
        data["api_key"] = "set" if self.api_key else None
        return data


def check_loopback(url: str) -> str:
    """``url`` without a trailing slash if it is http(s) on a loopback address, else raises."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise LoadTestError(f"--url must be http://host:port, not '{url}'")
    host = parts.hostname
    try:
        addresses = {ipaddress.ip_address(host)}
    except ValueError:
        try:
            infos = socket.getaddrinfo(host, parts.port or 80, proto=socket.IPPROTO_TCP)
        except OSError as exc:
            raise LoadTestError(f"cannot resolve '{host}': {exc}") from exc
        addresses = {ipaddress.ip_address(info[4][0]) for info in infos}
    if not addresses or not all(a.is_loopback for a in addresses):
        raise LoadTestError(
            f"refusing to load-test '{host}': the load test only targets a service on this "
            "machine (127.0.0.1, ::1 or localhost)"
        )
    return url.rstrip("/")


def make_config(args: argparse.Namespace) -> Config:
    """The run's parameters: explicit options, else the --quick or full defaults; bounded."""
    base = QUICK if args.quick else FULL

    def pick(name: str) -> Any:
        value = getattr(args, name)
        return base[name] if value is None else value

    config = Config(
        url=check_loopback(args.url),
        clients=int(pick("clients")),
        jobs=int(pick("jobs")),
        size=int(pick("size")),
        timeout_s=float(pick("timeout_s")),
        model=args.model,
        max_iterations=args.max_iterations,
        start_deg=float(pick("start_deg")),
        poll_interval_s=args.poll_interval_s,
        ramp_s=args.ramp_s,
        api_key=args.api_key or os.environ.get("PROXPOSE_API_KEY") or None,
        quick=args.quick,
    )
    limits = [
        (1 <= config.clients <= MAX_CLIENTS, f"--clients must be 1..{MAX_CLIENTS}"),
        (1 <= config.jobs <= MAX_JOBS, f"--jobs must be 1..{MAX_JOBS}"),
        (16 <= config.size <= 1024, "--size must be 16..1024 px"),
        (10.0 <= config.timeout_s <= MAX_TIMEOUT_S, f"--timeout-s must be 10..{MAX_TIMEOUT_S:g}"),
        (
            config.max_iterations is None or 1 <= config.max_iterations <= 100,
            "--max-iterations must be 1..100",
        ),
        (0.0 <= config.start_deg <= 30.0, "--start-deg must be 0..30"),
        (0.05 <= config.poll_interval_s <= 10.0, "--poll-interval-s must be 0.05..10"),
        (0.0 <= config.ramp_s <= config.timeout_s / 2, "--ramp-s must be 0..timeout/2"),
    ]
    for ok, message in limits:
        if not ok:
            raise LoadTestError(message)
    return config
