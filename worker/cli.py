"""The ``proxpose`` command line.

    proxpose estimate --model MESH --image REF --request REQUEST.json --output DIR
    proxpose render   --model MESH --request REQUEST.json --pose POSE.json --output IMG.png
    proxpose track    --model MESH --images DIR --request REQUEST.json --output OUT
    proxpose submit | status | wait | fetch | cancel | list | upload-model   (a running service)

Other subcommands (serve, worker, bench, loadtest) are registered by their own modules; each
is imported only when it runs, so ``estimate`` never loads the web stack and ``serve`` never
loads Mitsuba in the API process. The remote verbs (:mod:`service.client_cli`) need only the
client, so they work where only ``pip install proxpose`` was done.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

from pydantic import ValidationError

from schemas.version import __version__

#: Exit status for unusable input (bad file, bad JSON, failed validation).
EXIT_BAD_INPUT = 2
#: Exit status when the estimate itself fails (too few features, nothing visible, ...).
EXIT_FAILED = 1

Handler = Callable[[argparse.Namespace], int]
_EXTRA_COMMANDS: list[tuple[str, str, str]] = [
    # (name, module, help); the module defines add_arguments(parser) and run(args) -> int
    ("serve", "service.serve", "run the API, an embedded Redis and a worker"),
    ("worker", "worker.jobs.runner", "run an RQ worker against PROXPOSE_REDIS_URL"),
    ("bench", "worker.bench.cli", "accuracy and speed against the baselines"),
    ("loadtest", "service.loadtest", "load-test a running service"),
    (
        "migrate-blobs",
        "service.migrate_blobs",
        "move the bytes an older deployment kept in Redis to the blob store, then sweep it",
    ),
]


#: Packages of the extras: a command that needs a missing one says so instead of a traceback.
_EXTRA_PACKAGES = frozenset(
    {"numpy", "mitsuba", "drjit", "cv2", "trimesh", "PIL", "tqdm", "matplotlib"}
    | {"pydantic_settings", "redis", "rq", "fastapi", "starlette", "uvicorn", "prometheus_client"}
)


#: Module of the verbs that call a running service (submit, status, wait, fetch, ...).
_REMOTE_VERBS = "service.client_cli"


log = logging.getLogger("proxpose.cli")
_imported = time.monotonic()


def _process_age() -> float:
    """Seconds since this process started (Linux: from /proc, to 10 ms; elsewhere since this
    module was imported), for the timings ``-v`` logs."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return time.monotonic() - _imported


class BadInput(Exception):
    """A user error, reported in one line."""


def _validation_message(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"]) or "request"
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"{where}: {err['msg']}{more}"


def _read_json(path: Path, model: type) -> object:
    try:
        text = path.read_text()
    except OSError as exc:
        raise BadInput(f"cannot read {path}: {exc.strerror}") from exc
    try:
        return model.model_validate_json(text)  # type: ignore[attr-defined]
    except ValidationError as exc:
        raise BadInput(f"{path}: {_validation_message(exc)}") from exc


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise BadInput(f"cannot read {path}: {exc.strerror}") from exc


def _progress(enabled: bool) -> tuple[Callable[..., None] | None, Callable[[], None]]:
    if not enabled:
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=None, unit="it", desc="estimate", leave=False, file=sys.stderr)

    def update(rec: object, max_iterations: int) -> None:
        bar.total = max_iterations
        bar.set_postfix_str(
            f"{rec.stage} cost={rec.cost:.3g}px² features={rec.features}"  # type: ignore
        )
        bar.update(1)

    return update, bar.close


def cmd_estimate(args: argparse.Namespace) -> int:
    from schemas.estimate import EstimateRequest
    from worker.entry import run_estimate

    log.info("imports done %.2f s after the process started", _process_age())
    request = _read_json(args.request, EstimateRequest)
    image = _read_bytes(args.image)
    if not args.model.is_file():
        raise BadInput(f"model file not found: {args.model}")
    on_iteration, close = _progress(sys.stderr.isatty() and not args.quiet)
    try:
        result, artifacts = run_estimate(args.model, image, request, on_iteration)  # type: ignore
    finally:
        close()
    args.output.mkdir(parents=True, exist_ok=True)
    for name, png in artifacts.items():
        (args.output / f"{name}.png").write_bytes(png)
    (args.output / "result.json").write_text(result.model_dump_json(indent=2))
    log.info("wall %.2f s, of which the engine %.2f s", _process_age(), result.seconds)
    if args.json:
        print(result.model_dump_json(indent=2, by_alias=True))
        return 0
    err = result.errors
    extra = f", error {err.rotation_deg:.4f}° / {err.translation:.4g}" if err else ""
    print(
        f"{'converged' if result.converged else 'stopped'} ({result.reason}) after "
        f"{result.iterations} iterations, {result.renders} renders, {result.seconds:.1f} s"
        f"{extra} → {args.output / 'result.json'}"
    )
    return 0


def cmd_track(args: argparse.Namespace) -> int:
    from schemas.track import TrackFrame, TrackRequest
    from worker.engine.exceptions import InvalidInputError
    from worker.tracking import FrameFile, frame_files, run_track, track_csv, trajectory_png

    request = _read_json(args.request, TrackRequest)
    if not args.model.is_file():
        raise BadInput(f"model file not found: {args.model}")
    if not args.images.is_dir():
        raise BadInput(f"not a directory: {args.images}")
    paths = frame_files(args.images)
    if not paths:
        raise BadInput(f"{args.images}: no PNG, JPEG or TIFF frames")
    frames = [FrameFile(p.name, _read_bytes(p)) for p in paths]
    bar = None
    if sys.stderr.isatty() and not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=len(frames), unit="frame", desc="track", leave=False, file=sys.stderr)

    def on_frame(frame: TrackFrame) -> None:
        if bar is not None:
            bar.set_postfix_str(f"{frame.image} {frame.status} {frame.seconds:.2f}s")
            bar.update(1)

    try:
        result = run_track(args.model, frames, request, on_frame)  # type: ignore[arg-type]
    except InvalidInputError as exc:
        raise BadInput(str(exc)) from exc
    finally:
        if bar is not None:
            bar.close()
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "track.json").write_text(result.model_dump_json(indent=2))
    (args.output / "track.csv").write_text(track_csv(result))
    (args.output / "trajectory.png").write_bytes(trajectory_png(result))
    s = result.summary
    err = ""
    if s.median_rotation_error_deg is not None:
        err = (
            f", error median {s.median_rotation_error_deg:.4f}° / "
            f"{s.median_translation_pct_of_range:.4f} % (max {s.max_rotation_error_deg:.4f}°)"
        )
    print(
        f"{s.frames} frames: {s.tracked} tracked, {s.reinitialised} re-initialised, {s.lost} "
        f"lost; {s.converged} converged, {s.frames_per_second:.2f} frames/s{err} "
        f"→ {args.output / 'track.json'}"
    )
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from schemas.estimate import EstimateRequest
    from schemas.pose import Pose
    from schemas.render import RenderRequest
    from worker.entry import render_png

    request = _read_json(args.request, EstimateRequest)
    pose = _read_json(args.pose, Pose)
    if not args.model.is_file():
        raise BadInput(f"model file not found: {args.model}")
    render_request = RenderRequest(
        camera=request.camera,
        pose=pose,
        lighting=request.lighting,
        spp=args.spp,  # type: ignore
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(render_png(args.model, render_request))
    print(f"wrote {args.output}")
    return 0


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The whole parser. Given the command line it will parse, only that command's module is
    imported to register its arguments (the others are listed with their help alone): the
    load test's and the client's modules import httpx, 0.3 s of every ``proxpose estimate``."""
    chosen = _command_in(argv)
    parser = argparse.ArgumentParser(prog="proxpose", description=__doc__.split("\n\n")[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    parser.add_argument("--version", action="version", version=f"proxpose {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("estimate", help="estimate a pose from one image")
    p.add_argument("--model", type=Path, required=True, help="mesh: OBJ, PLY, STL, GLB, GLTF")
    p.add_argument("--image", type=Path, required=True, help="reference: PNG, JPEG or TIFF")
    p.add_argument("--request", type=Path, required=True, help="REQUEST.json")
    p.add_argument("--output", type=Path, required=True, help="directory for result + PNGs")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print result.json on stdout")
    p.set_defaults(handler=cmd_estimate)

    p = sub.add_parser("track", help="track the pose through an image sequence")
    p.add_argument("--model", type=Path, required=True, help="mesh: OBJ, PLY, STL, GLB, GLTF")
    p.add_argument("--images", type=Path, required=True, help="directory of frames, name order")
    p.add_argument(
        "--request", type=Path, required=True, help="REQUEST.json (ground_truth: a pose per frame)"
    )
    p.add_argument("--output", type=Path, required=True, help="directory for track.json + plots")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_track)

    p = sub.add_parser("render", help="render the model at a pose")
    p.add_argument("--model", type=Path, required=True)
    p.add_argument("--request", type=Path, required=True, help="camera and lighting")
    p.add_argument("--pose", type=Path, required=True, help="POSE.json: t + q|quaternion|R")
    p.add_argument("--output", type=Path, required=True, help="PNG to write")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    p.set_defaults(handler=cmd_render)

    import importlib
    import importlib.util

    # the remote verbs live with the client (loaded by name, like the commands below)
    importlib.import_module(_REMOTE_VERBS).add_commands(sub)
    for name, module, help_text in _EXTRA_COMMANDS:
        if importlib.util.find_spec(module) is None:
            continue
        p = sub.add_parser(name, help=help_text)
        p.set_defaults(handler=_lazy(module), module=module)
        if chosen in (None, name):
            _add_arguments(module, p)
    return parser


def _command_in(argv: list[str] | None) -> str | None:
    """The subcommand of a command line (its first word that is not an option: the global
    options take no value), or None when there is none or no command line was given."""
    return next((word for word in argv if not word.startswith("-")), None) if argv else None


def _add_arguments(module: str, parser: argparse.ArgumentParser) -> None:
    import importlib

    try:
        importlib.import_module(module).add_arguments(parser)
    except ImportError as exc:  # an extra that is not installed (pip install 'proxpose[all]')
        parser.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        parser.set_defaults(handler=_missing(exc.name or str(exc)))


def _missing(package: str) -> Handler:
    def run(args: argparse.Namespace) -> int:
        print(
            f"error: '{args.command}' needs {package}, which is not installed: "
            "pip install 'proxpose[all]'",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT

    return run


def _lazy(module: str) -> Handler:
    def run(args: argparse.Namespace) -> int:
        import importlib

        return int(importlib.import_module(module).run(args))

    return run


#: BLAS threads of the engine's processes: its matrices have six columns, and on a small machine
#: OpenBLAS's extra threads (spinning while they wait) cost more than they save and take cores
#: from the renderer (a RANSAC's residual product: 0.2 ms on one thread, 9 ms on two).
BLAS_THREADS = "1"


#: One-shot engine commands leave with ``os._exit`` once their output is flushed (see
#: :func:`run`): the interpreter's teardown of Dr.Jit (its kernels, recordings and threads)
#: took 0.3 s of every ``proxpose estimate`` (0.04 s without) and does nothing for anyone.
FAST_EXIT_COMMANDS = frozenset({"estimate", "render", "track"})


def run() -> None:
    """The ``proxpose`` console script: :func:`main`, then the process's exit."""
    code = main()  # returns only after its command line parsed: the command is the one named
    if _command_in(sys.argv[1:]) in FAST_EXIT_COMMANDS:
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except OSError:  # a reader that went away (e.g. `| head`)
                code = code or 1
        os._exit(code)
    sys.exit(code)


def main(argv: list[str] | None = None) -> int:
    # Before anything imports numpy (the subcommands' modules do); a value set outside wins.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", BLAS_THREADS)
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    from worker.engine.exceptions import EstimationCancelled, InvalidInputError, ProxposeError

    try:
        return int(args.handler(args))
    except ModuleNotFoundError as exc:
        if exc.name in _EXTRA_PACKAGES:
            print(
                f"error: '{args.command}' needs {exc.name}, which is not installed: "
                "pip install 'proxpose[all]' (the engine and the service)",
                file=sys.stderr,
            )
            return EXIT_BAD_INPUT
        raise
    except BadInput as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except InvalidInputError as exc:
        print(f"error: {exc} [{exc.code}]", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (ProxposeError, EstimationCancelled) as exc:
        print(f"error: {exc} [{exc.code}]", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    run()
