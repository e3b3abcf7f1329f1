"""``proxpose bench``: accuracy and speed of our estimator against the baselines, paired.

    proxpose bench [--quick | --full] [--robustness [--references A,B] [--starts offset,truth]]
                   [--models demo,iss,aura,phobos] [--methods default,fast,paper,pnp]
                   [--bands 3,10,20] [--cases N] [--size PX|WxH,...] [--seed S]
                   [--output DIR] [--jobs N]

Every method runs on the same seeded cases (:mod:`worker.bench.cases`), in this process unless
``--jobs`` > 1; DIR/bench.json, DIR/bench.md and DIR/error_vs_offset.png are written by
:mod:`worker.bench.outputs`. Only the standard library is imported at module level, because the
CLI imports this module to build its parser.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from worker.bench.config import (
    DEFAULT_BANDS,
    DEFAULT_METHODS,
    DEFAULT_OUTPUT,
    ROBUSTNESS_BAND,
    make_tasks,
    prepare,
)
from worker.bench.outputs import environment, print_summary, write_outputs

if TYPE_CHECKING:
    from worker.bench.cases import CaseOutcome, CaseTask

#: The public models' directory, relative to the repository (a sibling checkout).
SHARED_MODELS_DIR = Path(__file__).resolve().parents[3] / "shared" / "models"
#: Exit status for unusable arguments (as the CLI's other commands).
EXIT_USAGE = 2


def _csv(text: str) -> list[str]:
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise argparse.ArgumentTypeError("expected a comma-separated list")
    return items


def _sizes(text: str) -> list[list[int]]:
    sizes = []
    for item in _csv(text):
        w, sep, h = item.lower().partition("x")
        try:
            sizes.append([int(w), int(h) if sep else int(w)])
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected PX or WxH, got {item!r}") from exc
    return sizes


def _float_csv(text: str) -> list[float]:
    try:
        return [float(s) for s in _csv(text)]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected numbers, got {text!r}") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the ``bench`` options on its subparser."""
    _add_suite_arguments(parser)
    parser.add_argument(
        "--methods",
        type=_csv,
        default=DEFAULT_METHODS,
        help="rows: METHOD[:FIELD=VALUE...], e.g. default:n_samples=24 (default: %(default)s)",
    )
    parser.add_argument(
        "--bands",
        type=_float_csv,
        default=DEFAULT_BANDS,
        help="offset band edges: N = N° and N %% of range (default: %(default)s)",
    )
    parser.add_argument("--cases", type=int, help="cases per model and band (default 3)")
    parser.add_argument(
        "--size",
        type=_sizes,
        help="image sizes: PX (square) or WxH, comma-separated, e.g. 512,1024,1920x1200 "
        "(default 512); a non-square camera has its principal point off the centre",
    )
    parser.add_argument("--seed", type=int, default=0, help="suite seed (default 0)")
    parser.add_argument(
        "--offsets",
        choices=["uniform", "edge"],
        default="uniform",
        help="offset magnitude: uniform in (previous edge, edge], or at the edge",
    )
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT, help="output directory")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument(
        "--save-cases",
        choices=["none", "failed", "all"],
        default="failed",
        help="write cases (reference + requests) to DIR/cases for replay (default: failed)",
    )
    parser.add_argument(
        "--models-dir",
        type=Path,
        default=SHARED_MODELS_DIR,
        help="where iss, aura and phobos live (default: ../shared/models)",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_sequence_arguments(parser)
    parser.add_argument(
        "--sensor",
        action="store_true",
        help="only compare Mitsuba's batch sensor with separate perturbation renders",
    )


def _add_suite_arguments(parser: argparse.ArgumentParser) -> None:
    """Which suite: the preset, robustness or terrain, their references, starts and models."""
    suite = parser.add_mutually_exclusive_group()
    suite.add_argument("--quick", action="store_true", help="smoke test: demo sat, 1 case, 160 px")
    suite.add_argument("--full", action="store_true", help="10 cases per model and band")
    parser.add_argument(
        "--robustness",
        action="store_true",
        help="the robustness suite: references made with other physics, one class at a time "
        f"(offsets in ({ROBUSTNESS_BAND[0]:g}, {ROBUSTNESS_BAND[1]:g}]°), each estimate also "
        "started at the truth (the drift)",
    )
    parser.add_argument(
        "--references", type=_csv, help="reference classes of --robustness (default: all)"
    )
    parser.add_argument(
        "--starts",
        type=_csv,
        help="--robustness: start from the case's guess ('offset'), the true pose ('truth') or "
        "both (default: offset,truth)",
    )
    parser.add_argument(
        "--truth-seeds",
        type=int,
        default=1,
        help="estimates per case and method from the truth, each with another estimator seed: "
        "the drift's bias (where every seed goes) and spread (what the seed decides) are "
        "reported apart (default 1)",
    )
    parser.add_argument(
        "--models",
        type=_csv,
        help="demo, iss, aura, phobos, asteroid, terrain, terrain-ridged or mesh paths "
        "(default: demo, iss, aura, phobos)",
    )
    parser.add_argument(
        "--terrain",
        action="store_true",
        help="add the terrain band: a cratered heightfield filling the frame (models terrain and "
        "the held-out terrain-ridged), references ray traced with other physics, each estimate "
        "also started at the truth",
    )
    parser.add_argument(
        "--fill",
        type=float,
        help="the spacecraft cases' target diameter over the smaller image side (default 0.6; "
        "over 1 the target runs past the frame, as at docking range, e.g. 3)",
    )
    parser.add_argument(
        "--sun-elevation",
        type=_float_csv,
        help="LO,HI: the terrain band's sun elevation above the horizon, degrees, drawn uniformly "
        "(default 25,45; a low sun casts long shadows)",
    )
    parser.add_argument(
        "--altitude",
        type=_float_csv,
        help="LO,HI: the terrain band's camera height above the ground it looks at, metres, "
        "drawn uniformly (default 550,700; the demo terrain is 2 km across)",
    )
    parser.add_argument(
        "--tilt",
        type=_float_csv,
        help="LO,HI: the terrain band's camera tilt from the nadir, degrees, drawn uniformly "
        "(default 15,30; 0 looks straight down)",
    )


def _add_sequence_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--sequences",
        type=_csv,
        nargs="?",
        const=",".join(("approach", "flyaround", "tumble")),
        help="only the sequence suite: the tracker against chained estimates on these motions "
        "(default approach,flyaround,tumble; --models, --size, --seed apply; see --frames)",
    )
    parser.add_argument(
        "--frames", type=int, default=24, help="--sequences: frames per sequence (default 24)"
    )
    parser.add_argument("--no-chained", action="store_true", help="--sequences: the tracker only")


class Progress:
    """A tqdm bar over estimates, showing the case, the method and the successes so far."""

    def __init__(self, total: int, enabled: bool) -> None:
        from tqdm import tqdm

        self.bar = tqdm(
            total=total,
            unit="est",
            desc="bench",
            disable=not enabled,
            file=sys.stderr,
            dynamic_ncols=True,
        )
        self.done = 0
        self.successes = 0

    def starting(self, task: CaseTask) -> None:
        self.bar.set_postfix_str(f"{task.case_id}: rendering the reference")

    def record(self, record: dict[str, Any]) -> None:
        from worker.bench.stats import is_success

        self.done += 1
        self.successes += is_success(record)
        self.bar.set_postfix_str(
            f"{record['case_id']} {record['method']} · {self.successes}/{self.done} ok"
        )
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def run_serial(tasks: list[CaseTask], progress: Progress, done: dict[int, CaseOutcome]) -> None:
    """Every case in this process, into ``done`` (by task index): first every reference and
    full-render time, then the estimates (see :func:`worker.bench.cases.prepare_case`: a scene
    built between a warm-up and a timed estimate would put its kernels' recording in the
    timing)."""
    from worker.bench.cases import prepare_case, run_prepared

    prepared = []
    for task in tasks:
        progress.starting(task)
        prepared.append(prepare_case(task))
    for i, (task, case) in enumerate(zip(tasks, prepared, strict=True)):
        done[i] = run_prepared(task, case, progress.record)


def _init_worker(threads: int) -> None:
    import drjit as dr

    from worker.entry import init_renderer_backend

    init_renderer_backend()
    dr.set_thread_count(threads)


def run_parallel(
    tasks: list[CaseTask], progress: Progress, done: dict[int, CaseOutcome], jobs: int
) -> None:
    """Cases spread over ``jobs`` worker processes, into ``done`` (each warms up on its own).

    Timings then include contention between the workers; for timings, use ``--jobs 1``.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from worker.bench.cases import run_case

    threads = max(1, (os.cpu_count() or 1) // jobs)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(jobs, ctx, _init_worker, (threads,)) as pool:
        futures = {pool.submit(run_case, task): i for i, task in enumerate(tasks)}
        try:
            for future in as_completed(futures):
                outcome = done[futures[future]] = future.result()
                for record in outcome.records:
                    progress.record(record)
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def run_sensor_comparison(args: argparse.Namespace) -> int:
    """``--sensor``: batch sensor vs separate renders on the demo satellite, printed + JSON."""
    import json

    from worker.bench.sensor import compare
    from worker.demo.satellite import demo_satellite_path
    from worker.engine.meshes import load_model
    from worker.entry import init_renderer_backend

    variant = init_renderer_backend()
    rows = compare(load_model(demo_satellite_path(args.output / "models")))
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "sensor.json").write_text(json.dumps({"variant": variant, "rows": rows}))
    for r in rows:
        print(f"{variant} spp {r['spp']}: {r['views']} views at {r['size_px']} px: separate "
              f"{r['separate_s']:.3f} s, batch {r['batch_s']:.3f} s "
              f"(batch {r['batch_speedup']:.2f}x as fast)")  # fmt: skip
    return 0


def run_sequence_suite(args: argparse.Namespace) -> int:
    """``--sequences``: the tracker and chained estimates on rendered sequences."""
    from worker.bench.cases import BenchSetupError, resolve_models
    from worker.bench.sequences import MOTIONS
    from worker.bench.tracks import DEFAULT_REFERENCES, run_suite
    from worker.entry import init_renderer_backend

    bad = [m for m in args.sequences if m not in MOTIONS]
    if bad:
        print(f"error: --sequences: unknown motion {bad[0]!r} (know {', '.join(MOTIONS)})",
              file=sys.stderr)  # fmt: skip
        return EXIT_USAGE
    require = os.environ.get("PROXPOSE_REQUIRE_SHARED") == "1"
    try:
        models, skipped = resolve_models(
            args.models or ["iss", "aura"], args.models_dir, args.output / "models", require
        )
    except BenchSetupError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    for message in skipped:
        print(message, file=sys.stderr)
    variant = init_renderer_backend()
    sizes = [(w, h) for w, h in args.size] if args.size else [(512, 512)]
    if not all(32 <= n <= 4096 for size in sizes for n in size):
        print("error: --size: image sizes must be 32..4096 px", file=sys.stderr)
        return EXIT_USAGE
    references = args.references or list(DEFAULT_REFERENCES)
    shown = ", ".join(f"{w}x{h}" for w, h in sizes)
    print(f"sequence suite ({variant}, {shown} px, {args.frames} frames each)")
    run_suite(models, args.sequences, references, args.frames, sizes, args.seed, args.output,
              chained=not args.no_chained)  # fmt: skip
    print(f"wrote {args.output / 'sequences.json'}, sequences.md")
    return 0


def run(args: argparse.Namespace) -> int:
    """The ``bench`` command: run every case, then write the outputs (also when interrupted)."""
    if args.sensor:
        return run_sensor_comparison(args)
    if args.sequences:
        return run_sequence_suite(args)
    from worker.bench.cases import BenchSetupError
    from worker.entry import init_renderer_backend

    try:
        config, models = prepare(args)
    except BenchSetupError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    env = environment(init_renderer_backend())
    tasks = make_tasks(config, models, args.output.resolve())
    total = sum(len(task.starts) for task in tasks) * len(config["methods"])
    progress = Progress(total, enabled=not args.quiet)
    start, status = time.perf_counter(), "interrupted"
    done: dict[int, CaseOutcome] = {}
    try:
        if config["jobs"] == 1:
            run_serial(tasks, progress, done)
        else:
            run_parallel(tasks, progress, done, config["jobs"])
        status = "complete"
    except Exception as exc:  # the partial results are still written, then the error raised
        status = f"aborted by {type(exc).__name__}: {exc}"
        raise
    finally:  # also on Ctrl-C: what finished is written
        progress.close()
        env["elapsed_s"] = round(time.perf_counter() - start, 1)
        env["load_average_end"] = list(os.getloadavg())
        outcomes = [done[i] for i in sorted(done)]
        summary = write_outputs(args.output, outcomes, config, env, status)
    print_summary(summary, args.output)
    return 0
