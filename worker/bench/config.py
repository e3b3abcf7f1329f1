"""The bench's settings: suites, the checked configuration and the tasks it makes.

Only the standard library is imported at module level (the CLI builds its parser from these
names).
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from worker.bench.cases import CaseTask

ALL_MODELS = ["demo", "iss", "aura", "phobos"]
#: The terrain band's models (worker.bench.terrain): the demo terrain, a held-out generator.
TERRAIN_MODEL_NAMES = ("terrain", "terrain-ridged")
#: Offsets of the terrain band: (lo, hi] degrees and percent of the range.
TERRAIN_BAND = (2.0, 6.0)
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


def make_config(args: argparse.Namespace) -> dict[str, Any]:
    """The suite settings from the arguments (preset, then explicit values), checked."""
    from worker.bench.cases import BenchSetupError, band_edges, parse_method

    name = "quick" if args.quick else "full" if args.full else "small"
    preset = SUITES[name]
    robust = bool(args.robustness or args.references)
    cases = ROBUSTNESS_CASES if robust and name == "small" else preset["cases"]
    models = _models(args.models or preset["models"], getattr(args, "terrain", False))
    config = {
        "suite": f"robustness-{name}" if robust else name,
        "models": models,
        "methods": [parse_method(m).label for m in args.methods],
        "bands": [ROBUSTNESS_BAND[1]] if robust else args.bands,
        "references": _references(args.references) if robust else ["standard"],
        "starts": _starts(args.starts) if robust else ["offset"],
        "truth_seeds": getattr(args, "truth_seeds", 1),
        "cases": cases if args.cases is None else args.cases,
        "sizes": [[preset["size_px"]] * 2] if args.size is None else args.size,
        "seed": args.seed,
        "offsets": args.offsets,
        "jobs": args.jobs,
        "save_cases": args.save_cases,
        **_terrain_view(args, models),
        "fill": _fill(getattr(args, "fill", None)),
    }
    band_edges(config["bands"])
    if len(set(config["methods"])) != len(config["methods"]):
        raise BenchSetupError("a method is listed twice")
    for key, lo, hi in (("cases", 1, 10_000), ("jobs", 1, 256), ("truth_seeds", 1, 100)):
        if not lo <= config[key] <= hi:
            raise BenchSetupError(f"{key} must be in {lo}..{hi}, got {config[key]}")
    truth_starts = "truth" in config["starts"] or set(models) & set(TERRAIN_MODEL_NAMES)
    if config["truth_seeds"] > 1 and not truth_starts:
        raise BenchSetupError(
            "--truth-seeds needs estimates from the truth: --robustness (its starts include "
            "'truth' by default) or --terrain"
        )
    for w, h in config["sizes"]:
        if not (32 <= w <= 4096 and 32 <= h <= 4096):
            raise BenchSetupError(f"image sizes must be 32..4096 px, got {w}x{h}")
    if not 0 <= config["seed"] < 2**32:
        raise BenchSetupError("seed must be in 0..2³²−1")
    return config


def _models(names: list[str], terrain: bool) -> list[str]:
    """The suite's models, with the terrain band's appended when asked for (``--terrain``)."""
    return names + [m for m in TERRAIN_MODEL_NAMES if terrain and m not in names]


#: The terrain view's ranges: config key, option (and args attribute), unit, bounds, and
#: whether LO may equal the lower bound (a tilt of 0 looks straight down).
_TERRAIN_RANGES = (
    ("sun_elevation_deg", "--sun-elevation", "degrees", (0.0, 90.0), False),
    ("altitude_m", "--altitude", "metres", (0.0, 1e6), False),
    ("tilt_deg", "--tilt", "degrees", (0.0, 80.0), True),
)


def _terrain_view(args: argparse.Namespace, models: list[str]) -> dict[str, list[float]]:
    """The terrain band's view ranges (worker.bench.terrain.TerrainView), each LO,HI within
    its bounds, asked for only with a terrain model among ``models``; the defaults where not
    asked for."""
    from worker.bench.cases import BenchSetupError
    from worker.bench.terrain import TerrainView

    view = asdict(TerrainView())
    out: dict[str, list[float]] = {}
    for key, option, unit, (lo, hi), lo_ok in _TERRAIN_RANGES:
        values = getattr(args, option[2:].replace("-", "_"), None)
        out[key] = list(view[key]) if values is None else values
        if values is None:
            continue
        if not set(models) & set(TERRAIN_MODEL_NAMES):
            raise BenchSetupError(
                f"{option} applies to the terrain band: add --terrain (or --models terrain)"
            )
        ok = len(values) == 2 and values[0] <= values[1] < hi
        if not (ok and (values[0] >= lo if lo_ok else values[0] > lo)):
            raise BenchSetupError(
                f"{option} must be LO,HI {unit} with {lo:g} {'<=' if lo_ok else '<'} LO <= HI "
                f"< {hi:g}, got {values}"
            )
    return out


def _fill(value: float | None) -> float:
    """The spacecraft cases' target size: its diameter over the smaller image side (default
    CaseSpec's 0.6; over 1 the target runs past the frame, as at docking range)."""
    from worker.bench.cases import BenchSetupError
    from worker.bench.synth import CaseSpec

    if value is None:
        return CaseSpec(0.0, 0.0).fill
    if not 0.05 <= value <= 10.0:
        raise BenchSetupError(f"--fill must be in 0.05..10 (diameter / image side), got {value:g}")
    return float(value)


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
    (model, reference class, case index), each run from its guess and from the truth; for a
    terrain model one per case index in the terrain band, from its guess and from the truth."""
    from worker.bench.cases import CaseTask, band_edges, parse_method
    from worker.bench.terrain import TerrainView

    methods = [parse_method(m) for m in config["methods"]]
    robust = config["references"] != ["standard"]
    bands = [ROBUSTNESS_BAND] if robust else band_edges(config["bands"])
    starts = tuple(config["starts"])
    terrain = {"references": ["terrain"], "bands": [TERRAIN_BAND], "starts": ("offset", "truth")}
    spacecraft = {"references": config["references"], "bands": bands, "starts": starts}

    def plan(name: str) -> dict[str, Any]:
        return terrain if name in TERRAIN_MODEL_NAMES else spacecraft

    return [
        CaseTask(
            model=name,
            model_path=str(path),
            band=hi,
            band_lo=lo,
            index=i,
            width_px=w,
            height_px=h,
            sized=len(config["sizes"]) > 1,
            seed=config["seed"],
            offsets=config["offsets"],
            methods=methods,
            output_dir=str(output_dir),
            save_cases=config["save_cases"],
            reference=reference,
            starts=plan(name)["starts"],
            terrain_view=TerrainView(**{key: tuple(config[key]) for key, *_ in _TERRAIN_RANGES}),
            fill=config["fill"],
            truth_seeds=config.get("truth_seeds", 1),
        )
        for w, h in config["sizes"]
        for name, path in models
        for reference in plan(name)["references"]
        for lo, hi in plan(name)["bands"]
        for i in range(config["cases"])
    ]


def _case_conditions(config: dict[str, Any]) -> dict[str, Any]:
    from worker.bench.cases import CAMERA_FOV_DEG, bench_camera
    from worker.bench.synth import CaseSpec

    spec = asdict(CaseSpec(0.0, 0.0, fill=config["fill"]))
    del spec["offset_deg"], spec["offset_frac"]
    return {
        "cameras": [bench_camera(w, h).model_dump() for w, h in config["sizes"]],
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
