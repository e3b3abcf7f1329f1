"""The ``proxpose`` verbs that call a running service through :mod:`service.client`:

    proxpose submit --url URL --model-id demo-sat --image ref.png --request REQUEST.json
    proxpose status ID        proxpose wait ID [--timeout S]
    proxpose fetch ID NAME -o difference.png        proxpose cancel ID
    proxpose list [--status S] [--model-id M]       proxpose upload-model MESH [--name N]

``--url`` defaults to $PROXPOSE_URL (else http://127.0.0.1:8000), ``--api-key`` to
$PROXPOSE_API_KEY. ``--json`` prints the service's JSON instead of a line for people. The
service's errors are printed with their code and each bad field; the exit status is 2 for a
request the service refused (4xx), 1 for a job that did not succeed or a service that cannot be
reached. Importing this module imports nothing but the standard library: the client is loaded
when a verb runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from service.client import Client

#: Exit status of a request the service refused (a 4xx answer).
EXIT_REFUSED = 2
#: Exit status of a job that did not succeed, or of a service that cannot be reached.
EXIT_FAILED = 1
DEFAULT_URL = "http://127.0.0.1:8000"


def add_commands(sub: Any) -> None:
    """Register the remote verbs on the ``proxpose`` sub-parsers."""
    p = _verb(sub, "submit", "submit an estimate to a running service", _submit)
    p.add_argument("--image", type=Path, required=True, help="reference: PNG, JPEG or TIFF")
    p.add_argument("--request", type=Path, required=True, help="REQUEST.json (EstimateCreate)")
    p.add_argument("--model-id", help="model id (overrides the request's model_id)")
    p.add_argument("--idempotency-key", help="makes a retried submission return the same job")
    p.add_argument("--wait", action="store_true", help="wait for the job to end")

    p = _verb(sub, "status", "show an estimate of a running service", _status)
    p.add_argument("job_id")

    p = _verb(sub, "wait", "wait for an estimate to end (progress on stderr)", _wait)
    p.add_argument("job_id")
    p.add_argument("--timeout", type=float, help="give up after this many seconds")

    p = _verb(sub, "fetch", "download an artifact (PNG) or the result of an estimate", _fetch)
    p.add_argument("job_id")
    p.add_argument("name", help="artifact name (difference, final_render, ...) or 'result'")
    p.add_argument("-o", "--output", type=Path, help="file to write (default NAME.png / .json)")

    p = _verb(sub, "cancel", "cancel a queued or running estimate", _cancel)
    p.add_argument("job_id")

    p = _verb(sub, "list", "list the estimates of a running service", _list)
    p.add_argument("--status", action="append", help="only this status (repeatable)")
    p.add_argument("--model-id", help="only this model")
    p.add_argument("--limit", type=int, default=20)

    p = _verb(sub, "upload-model", "register a model file with a running service", _upload)
    p.add_argument("file", type=Path)
    p.add_argument("--name")


def _verb(
    sub: Any, name: str, help_text: str, handler: Callable[[Client, argparse.Namespace], int]
) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(name, help=help_text)
    p.add_argument("--url", default=os.environ.get("PROXPOSE_URL", DEFAULT_URL))
    p.add_argument("--api-key", default=os.environ.get("PROXPOSE_API_KEY"))
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=lambda args: _run(handler, args))
    return p


def _run(handler: Callable[[Client, argparse.Namespace], int], args: argparse.Namespace) -> int:
    from service.client import ApiError, Client, ProxposeClientError

    try:
        with Client(args.url, api_key=args.api_key) as client:
            return handler(client, args)
    except ApiError as exc:
        print(f"error: {exc.problem.detail} [{exc.code}, HTTP {exc.status}]", file=sys.stderr)
        for field in exc.errors:
            where = ".".join(str(p) for p in field.loc)
            print(f"  {where}: {field.msg} [{field.type}]", file=sys.stderr)
        return EXIT_REFUSED if exc.status < 500 else EXIT_FAILED
    except ProxposeClientError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_REFUSED


def _print(args: argparse.Namespace, model: Any, line: str) -> None:
    print(model.model_dump_json(indent=2, by_alias=True) if args.json else line)


def _job_line(job: Any) -> str:
    progress = job.progress
    line = f"{job.id} {job.status} iteration {progress.iteration}/{progress.max_iterations}"
    if job.error is not None:
        line += f" error {job.error.code}: {job.error.message}"
    if job.result is not None:
        r = job.result
        line += f" converged={r.converged} ({r.reason}) t={r.pose.t} q={r.pose.quaternion}"
    return line


def _submit(client: Client, args: argparse.Namespace) -> int:
    request = json.loads(args.request.read_text())
    if args.model_id:
        request["model_id"] = args.model_id
    job = client.submit_estimate(args.image, request, idempotency_key=args.idempotency_key)
    if args.wait:
        return _finish(client, job.id, args, None)
    _print(args, job, job.id)
    return 0


def _status(client: Client, args: argparse.Namespace) -> int:
    job = client.get(args.job_id)
    _print(args, job, _job_line(job))
    return 0


def _wait(client: Client, args: argparse.Namespace) -> int:
    return _finish(client, args.job_id, args, args.timeout)


def _finish(client: Client, job_id: str, args: argparse.Namespace, timeout_s: float | None) -> int:
    job = None
    if timeout_s is None:
        try:
            for event in client.events(job_id):
                job = event.job or job
                if event.progress is not None and not args.json:
                    p = event.progress
                    cost = f"{p.cost:.4g}" if p.cost is not None else "-"
                    print(
                        f"iteration {p.iteration}/{p.max_iterations} {p.stage} cost {cost} px²",
                        file=sys.stderr,
                    )
        except Exception as exc:  # the stream is a nicety: wait() polls without it
            print(f"note: no event stream ({exc}); polling", file=sys.stderr)
    if job is None:
        job = client.wait(job_id, timeout_s=timeout_s)
    _print(args, job, _job_line(job))
    return 0 if job.status == "succeeded" else EXIT_FAILED


def _fetch(client: Client, args: argparse.Namespace) -> int:
    if args.name == "result":
        job = client.get(args.job_id)
        if job.result is None:
            print(f"error: estimate {job.id} has no result ({job.status})", file=sys.stderr)
            return EXIT_FAILED
        data = job.result.model_dump_json(indent=2, by_alias=True).encode()
        out = args.output or Path("result.json")
    else:
        data = client.artifact(args.job_id, args.name)
        out = args.output or Path(f"{args.name.removesuffix('.png')}.png")
    out.write_bytes(data)
    print(json.dumps({"path": str(out), "bytes": len(data)}) if args.json else f"wrote {out}")
    return 0


def _cancel(client: Client, args: argparse.Namespace) -> int:
    job = client.cancel(args.job_id)
    _print(args, job, _job_line(job))
    return 0


def _list(client: Client, args: argparse.Namespace) -> int:
    page = client.list(status=args.status, model_id=args.model_id, limit=args.limit)
    lines = "\n".join(
        f"{j.id} {j.status} {j.model_id} {j.created_at:%Y-%m-%d %H:%M}" for j in page.items
    )
    _print(args, page, lines or "no estimates")
    return 0


def _upload(client: Client, args: argparse.Namespace) -> int:
    model = client.upload_model(args.file, name=args.name)
    _print(args, model, f"{model.id} {model.name} ({model.faces} faces)")
    return 0
