"""``proxpose bench``: accuracy and speed of our estimator against the baselines, paired.

    proxpose bench [--quick | --full] [--models demo,iss,aura,phobos]
                   [--methods default,fast,paper,pnp] [--bands 3,10,20] [--cases N] [--size PX]
                   [--seed S] [--output DIR] [--jobs N]

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
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from worker.bench.outputs import environment, print_summary, write_outputs

if TYPE_CHECKING:
    from worker.bench.cases import CaseOutcome, CaseTask

ALL_MODELS = ["demo", "iss", "aura", "phobos"]
#: Suite presets; an explicit --models/--cases/--size overrides the preset's value.
SUITES: dict[str, dict[str, Any]] = {
    "quick": {"models": ["demo"], "cases": 1, "size_px": 160},
    "small": {"models": ALL_MODELS, "cases": 3, "size_px": 512},
    "full": {"models": ALL_MODELS, "cases": 10, "size_px": 512},
}
#: The robustness suite's initial offsets: (lo, hi] degrees and percent of the range.
ROBUSTNESS_BAND = (3.0, 10.0)
#: Cases per model and reference class in the robustness suite (2 starts each).
ROBUSTNESS_CASES = 2
DEFAULT_METHODS = "default,fast,paper,pnp"
DEFAULT_BANDS = "3,10,20"
DEFAULT_OUTPUT = Path("bench-output")
#: The public models' directory, relative to the repository (a sibling checkout).
SHARED_MODELS_DIR = Path(__file__).resolve().parents[3] / "shared" / "models"
#: Exit status for unusable arguments (as the CLI's other commands).
EXIT_USAGE = 2


def _csv(text: str) -> list[str]:
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise argparse.ArgumentTypeError("expected a comma-separated list")
    return items


def _float_csv(text: str) -> list[float]:
    try:
        return [float(s) for s in _csv(text)]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected numbers, got {text!r}") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the ``bench`` options on its subparser."""
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
        "--models", type=_csv, help="demo, iss, aura, phobos or mesh paths (default: all)"
    )
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
    parser.add_argument("--size", type=int, help="image side, px (default 512)")
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
    parser.add_argument(
        "--sensor",
        action="store_true",
        help="only compare Mitsuba's batch sensor with separate perturbation renders",
    )


def make_config(args: argparse.Namespace) -> dict[str, Any]:
    """The suite settings from the arguments (preset, then explicit values), checked."""
    from worker.bench.cases import BenchSetupError, band_edges, parse_method

    name = "quick" if args.quick else "full" if args.full else "small"
    preset = SUITES[name]
    robust = bool(args.robustness or args.references)
    cases = ROBUSTNESS_CASES if robust and name == "small" else preset["cases"]
    config = {
        "suite": f"robustness-{name}" if robust else name,
        "models": args.models or preset["models"],
        "methods": [parse_method(m).label for m in args.methods],
        "bands": [ROBUSTNESS_BAND[1]] if robust else args.bands,
        "references": _references(args.references) if robust else ["standard"],
        "starts": _starts(args.starts) if robust else ["offset"],
        "cases": cases if args.cases is None else args.cases,
        "size_px": preset["size_px"] if args.size is None else args.size,
        "seed": args.seed,
        "offsets": args.offsets,
        "jobs": args.jobs,
        "save_cases": args.save_cases,
    }
    band_edges(config["bands"])
    if len(set(config["methods"])) != len(config["methods"]):
        raise BenchSetupError("a method is listed twice")
    for key, lo, hi in (("cases", 1, 10_000), ("size_px", 32, 4096), ("jobs", 1, 256)):
        if not lo <= config[key] <= hi:
            raise BenchSetupError(f"{key} must be in {lo}..{hi}, got {config[key]}")
    if not 0 <= config["seed"] < 2**32:
        raise BenchSetupError("seed must be in 0..2³²−1")
    return config


def _references(names: list[str] | None) -> list[str]:
    from worker.bench.cases import BenchSetupError
    from worker.bench.references import REFERENCE_CLASSES

    unknown = sorted(set(names or []) - set(REFERENCE_CLASSES))
    if unknown:
        known = ", ".join(REFERENCE_CLASSES)
        raise BenchSetupError(f"unknown reference class {unknown[0]!r} (known: {known})")
    return names or list(REFERENCE_CLASSES)


def _starts(names: list[str] | None) -> list[str]:
    from worker.bench.cases import BenchSetupError

    starts = names or ["offset", "truth"]
    if not set(starts) <= {"offset", "truth"} or len(set(starts)) != len(starts):
        raise BenchSetupError(f"starts must be 'offset' and/or 'truth', got {starts}")
    return starts


def make_tasks(
    config: dict[str, Any], models: list[tuple[str, Path]], output_dir: Path
) -> list[CaseTask]:
    """One task per (model, band, case index), in that order; for the robustness suite one per
    (model, reference class, case index), each run from its guess and from the truth."""
    from worker.bench.cases import CaseTask, band_edges, parse_method

    methods = [parse_method(m) for m in config["methods"]]
    robust = config["references"] != ["standard"]
    bands = [ROBUSTNESS_BAND] if robust else band_edges(config["bands"])
    starts = tuple(config["starts"])
    return [
        CaseTask(
            model=name,
            model_path=str(path),
            band=hi,
            band_lo=lo,
            index=i,
            size_px=config["size_px"],
            seed=config["seed"],
            offsets=config["offsets"],
            methods=methods,
            output_dir=str(output_dir),
            save_cases=config["save_cases"],
            reference=reference,
            starts=starts,
        )
        for name, path in models
        for reference in config["references"]
        for lo, hi in bands
        for i in range(config["cases"])
    ]


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
    """Every case in this process, in order, into ``done`` (by task index)."""
    from worker.bench.cases import run_case

    for i, task in enumerate(tasks):
        progress.starting(task)
        done[i] = run_case(task, progress.record)


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


def _case_conditions(config: dict[str, Any]) -> dict[str, Any]:
    from worker.bench.cases import CAMERA_FOV_DEG, bench_camera
    from worker.bench.synth import CaseSpec

    spec = asdict(CaseSpec(0.0, 0.0))
    del spec["offset_deg"], spec["offset_frac"]
    return {
        "camera": bench_camera(config["size_px"]).model_dump(),
        "fov_deg": CAMERA_FOV_DEG,
        "reference": spec,
    }


def prepare(args: argparse.Namespace) -> tuple[dict[str, Any], list[tuple[str, Path]]]:
    """The checked suite settings and the models' paths (absent shared models skipped).

    Raises
    ------
    BenchSetupError
        When an argument is unusable or no model is left to bench.
    """
    from schemas.settings import get_settings
    from worker.bench.cases import BenchSetupError, resolve_models

    config = make_config(args)
    require = os.environ.get("PROXPOSE_REQUIRE_SHARED") == "1"
    data_dir = get_settings().data_dir
    models, skipped = resolve_models(config["models"], args.models_dir, data_dir, require)
    for message in skipped:
        print(message, file=sys.stderr)
    if not models:
        raise BenchSetupError("no model left to bench")
    config["models"] = [name for name, _ in models]
    if len(set(config["models"])) != len(models):
        raise BenchSetupError(f"a model is listed twice: {config['models']}")
    config["skipped_models"] = skipped
    config["conditions"] = _case_conditions(config)
    return config, models


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


def run(args: argparse.Namespace) -> int:
    """The ``bench`` command: run every case, then write the outputs (also when interrupted)."""
    if args.sensor:
        return run_sensor_comparison(args)
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
