"""Bench cases: the models, the seeded cases in offset bands, and one estimate per method.

A case is one reference image (``worker.bench.synth.make_case``: another renderer setup, noise,
exposure, a sun-direction error) with one initial guess; every method is run on the same case,
so the comparison is paired. The initial offset of a case in band ``(lo, hi]`` is drawn
uniformly in that interval, the rotation angle in degrees and the translation in percent of the
range independently (``offsets="edge"`` puts both exactly at ``hi``). Seeds depend only on the
suite seed, the model name, the band and the case index, so adding a model or raising the case
count leaves every other case unchanged.
"""

from __future__ import annotations

import json
import logging
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from schemas.camera import Camera
from schemas.options import EstimateOptions
from worker.bench.costs import (
    full_render_seconds,
    peak_memory_mb,
    reset_peak_memory,
    resident_memory_mb,
)
from worker.bench.records import failure, outcome
from worker.bench.synth import Case, CaseSpec, from_truth, make_case
from worker.bench.terrain import TERRAIN_MODELS, TerrainView, make_terrain_case, terrain_model_path
from worker.engine.meshes import LoadedModel
from worker.engine.metrics import rotation_error_deg, speed_score, translation_error
from worker.engine.posemath import pose_from_schema

log = logging.getLogger(__name__)

DEMO_MODEL = "demo"
#: The procedural small body (worker.demo.asteroid), held out of the estimator's tuning.
ASTEROID_MODEL = "asteroid"
#: Public models under the shared models directory, by bench name.
SHARED_MODEL_FILES = {
    "iss": "iss/iss_clean.glb",
    "aura": "aura/aura.glb",
    "phobos": "phobos/24878_Phobos_1_1000.glb",
}
#: Horizontal and vertical field of view of the bench camera (square pixels, centred), degrees.
CAMERA_FOV_DEG = 30.0


class BenchSetupError(ValueError):
    """A bench argument is unusable (unknown method or option, missing required model)."""


@dataclass
class MethodSpec:
    """A method row: a method preset plus option overrides, e.g. ``default:n_samples=24``."""

    label: str
    method: str
    overrides: dict[str, Any] = field(default_factory=dict)

    def options(self, **extra: Any) -> EstimateOptions:
        """The estimate options of this row; ``extra`` fields win over the overrides."""
        return EstimateOptions.model_validate({"method": self.method, **self.overrides, **extra})


def parse_method(spec: str) -> MethodSpec:
    """Parse ``METHOD[:FIELD=VALUE]...`` (values read as JSON when they parse, else strings).

    Raises
    ------
    BenchSetupError
        When the method or a field is unknown or a value is out of range.
    """
    name, *pairs = spec.strip().split(":")
    overrides: dict[str, Any] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        if not sep or not key:
            raise BenchSetupError(f"method {spec!r}: expected FIELD=VALUE, got {pair!r}")
        try:
            overrides[key] = json.loads(raw)
        except json.JSONDecodeError:
            overrides[key] = raw
    method = MethodSpec(spec.strip(), name, overrides)
    try:
        method.options()
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        raise BenchSetupError(f"method {spec!r}: {exc}") from exc
    return method


def band_edges(bands: Sequence[float]) -> list[tuple[float, float]]:
    """``(lo, hi]`` per band: from the previous band's edge (0 for the first) to its own."""
    if not bands or any(b <= 0 for b in bands) or sorted(set(bands)) != list(bands):
        raise BenchSetupError(f"bands must be positive and increasing, got {bands}")
    return list(zip([0.0, *bands[:-1]], bands, strict=True))


def case_seeds(seed: int, model: str, band: float, index: int) -> tuple[int, int, int]:
    """Seeds (reference and truth, offset magnitudes, estimator) of one case."""
    entropy = [seed, zlib.crc32(model.encode()), round(band * 1000), index]
    a, b, c = np.random.SeedSequence(entropy).generate_state(3)
    return int(a), int(b), int(c) % 2**31


def draw_offset(lo: float, hi: float, draw: str, rng: np.random.Generator) -> tuple[float, float]:
    """Initial offset (rotation deg, translation fraction of the range) in band ``(lo, hi]``."""
    if draw == "edge":
        return hi, hi / 100.0
    rot_deg, trans_pct = hi - rng.uniform(0.0, hi - lo, size=2)  # (lo, hi], never exactly lo
    return float(rot_deg), float(trans_pct) / 100.0


def resolve_models(
    names: list[str], models_dir: Path, data_dir: Path, require_shared: bool
) -> tuple[list[tuple[str, Path]], list[str]]:
    """Paths of the bench models, and a message per model skipped because its file is absent.

    ``demo`` is the procedural satellite, ``asteroid`` the procedural small body and
    ``terrain``, ``terrain-ridged`` the procedural terrains (written under ``data_dir`` on
    first use), ``iss``,
    ``aura``, ``phobos`` are looked up in ``models_dir``; any other name is a mesh file path.
    """
    found: list[tuple[str, Path]] = []
    skipped: list[str] = []
    for name in names:
        if name in TERRAIN_MODELS:
            found.append((name, terrain_model_path(name, data_dir).resolve()))
            continue
        if name == DEMO_MODEL:
            from worker.demo.satellite import demo_satellite_path

            found.append((name, demo_satellite_path(data_dir).resolve()))
            continue
        if name == ASTEROID_MODEL:
            from worker.demo.asteroid import asteroid_path

            found.append((name, asteroid_path(data_dir).resolve()))
            continue
        path = models_dir / SHARED_MODEL_FILES[name] if name in SHARED_MODEL_FILES else Path(name)
        label = name if name in SHARED_MODEL_FILES else path.stem
        if path.is_file():
            found.append((label, path.resolve()))
        elif require_shared or name not in SHARED_MODEL_FILES:
            raise BenchSetupError(f"model {name!r}: {path} not found")
        else:
            skipped.append(f"skipping model {name!r}: {path} not found")
    return found, skipped


def bench_camera(width_px: int, height_px: int | None = None) -> Camera:
    """A camera with a CAMERA_FOV_DEG field of view across its short side: square and centred
    (``height_px`` None), or, when it is not square, with its principal point off the centre
    (3 % of the width right, 2 % of the height up), as calibrated cameras have."""
    height = width_px if height_px is None else height_px
    f = 0.5 * min(width_px, height) / np.tan(np.radians(0.5 * CAMERA_FOV_DEG))
    cx, cy = 0.5 * (width_px - 1), 0.5 * (height - 1)
    if height != width_px:
        cx, cy = cx + 0.03 * width_px, cy - 0.02 * height
    return Camera(width=width_px, height=height, fx=float(f), fy=float(f), cx=cx, cy=cy)


@dataclass
class CaseTask:
    """Everything one case needs; plain data, so it can be sent to a worker process."""

    model: str
    model_path: str
    band: float
    band_lo: float
    index: int
    width_px: int
    height_px: int
    seed: int
    offsets: str
    methods: list[MethodSpec]
    output_dir: str | None = None
    save_cases: str = "failed"
    #: "standard", or a class of worker.bench.references (the robustness suite).
    reference: str = "standard"
    #: "offset": from the case's initial guess; "truth": from the true pose (the drift).
    starts: tuple[str, ...] = ("offset",)
    terrain_view: TerrainView | None = None  # terrain: sun elevation, altitude, tilt ranges
    fill: float = 0.6  # spacecraft: diameter / smaller image side (> 1: past the frame)
    #: Whether the case id names its size (a suite of several sizes).
    sized: bool = False
    #: Estimates per method from the truth, each with another estimator seed (the spread of
    #: where they end tells the bias from the seed's part: worker.bench.stats).
    truth_seeds: int = 1

    @property
    def size(self) -> str:
        return f"{self.width_px}x{self.height_px}"

    @property
    def case_id(self) -> str:
        where = self.reference if self.reference != "standard" else f"b{self.band:g}"
        size = f"-{self.size}" if self.sized else ""
        return f"{self.model}-{where}{size}-{self.index:02d}"


@dataclass
class CaseOutcome:
    """The records of one case (one per method) and the warm-ups run before it, if any."""

    records: list[dict[str, Any]]
    warmups: list[dict[str, Any]]


RecordCallback = Callable[[dict[str, Any]], None]
#: (model path, method label, image size) warmed up in this process.
_warmed: set[tuple[str, str, str]] = set()


def build_case(task: CaseTask, model: LoadedModel) -> tuple[Case, int]:
    """The case of ``task`` (reference, request, truth) and its estimator seed."""
    ref_seed, offset_seed, est_seed = case_seeds(task.seed, task.model, task.band, task.index)
    rot_deg, frac = draw_offset(
        task.band_lo, task.band, task.offsets, np.random.default_rng(offset_seed)
    )
    camera = bench_camera(task.width_px, task.height_px)
    spec = CaseSpec(rot_deg, frac, fill=task.fill)
    if task.reference == "terrain":
        return make_terrain_case(model, camera, spec, ref_seed, view=task.terrain_view), est_seed
    return make_case(model, camera, spec, ref_seed, reference=task.reference), est_seed


@dataclass
class PreparedCase:
    """A case made and measured, ready for its estimates: the model it was made from, its
    reference, the estimator seed and the time of one full-resolution render."""

    model: LoadedModel
    case: Case
    est_seed: int
    render_s: float


def prepare_case(task: CaseTask) -> PreparedCase:
    """Render the reference of ``task`` and time one full-resolution render of its model.

    Both build Mitsuba scenes, and building any scene makes every render kernel recorded
    before it record again on its next call (Dr.Jit's frozen functions see the new objects;
    1–3 s of the next ISS or Phobos estimate at 512²). So a serial run prepares every case
    first (``worker.bench.cli.run_serial``) and no scene is built between a method's warm-up
    and its timed estimates, as in a worker that has served the model and camera before."""
    from worker.engine.meshes import load_model

    model = load_model(task.model_path)  # cached by content across the run's cases
    case, est_seed = build_case(task, model)
    return PreparedCase(model, case, est_seed, full_render_seconds(model, case.request))


def run_case(task: CaseTask, on_record: RecordCallback | None = None) -> CaseOutcome:
    """Prepare the case of ``task`` and run every method on it (see :func:`run_prepared`)."""
    return run_prepared(task, prepare_case(task), on_record)


def run_prepared(
    task: CaseTask, prepared: PreparedCase, on_record: RecordCallback | None = None
) -> CaseOutcome:
    """Run every method on a prepared case, warming each (model, method, size) up once."""
    model, case = prepared.model, prepared.case
    reference = case.reference.astype(np.float32) / 255.0  # as decode_image reads an 8-bit PNG
    new = [spec for spec in task.methods if (task.model_path, spec.label, task.size) not in _warmed]
    # Twice round when several methods are new: a method's renders after another method's
    # record their kernels again (Dr.Jit keeps a recording per state it has seen, so this
    # settles after one more round: ISS 512², default after pnp 2.6 s, then 1.1 s)
    rounds = 2 if len(new) > 1 else 1
    warmups = [
        warm_up(model, task.model_path, reference, case, spec)
        for _ in range(rounds)
        for spec in new
    ]
    _warmed.update((task.model_path, spec.label, task.size) for spec in new)
    records = []
    for start in task.starts:
        started = case if start == "offset" else from_truth(case)
        fields = {**_case_fields(task, started), "start": start, "render_s": prepared.render_s}
        for reseed in range(task.truth_seeds if start == "truth" else 1):
            for spec in task.methods:
                record = run_method(
                    model, reference, started, spec, prepared.est_seed, fields, reseed
                )
                records.append(record)
                if on_record is not None:
                    on_record(record)
    if task.output_dir and task.save_cases != "none":
        from worker.bench.saved import save_case

        save_case(task, case, records)
    return CaseOutcome(records, warmups)


def warm_up(
    model: LoadedModel, model_path: str, reference: np.ndarray, case: Case, spec: MethodSpec
) -> dict[str, Any]:
    """One untimed estimate of the case per model, method and image size, so that scene builds
    and first-call costs stay out of the timings: it builds the scenes and records every render
    kernel the method uses at that size (a one-iteration warm-up left the refinement's kernels
    to the first timed estimate: 2.4 s of its 5.7 s on an ISS case at 640×480), as a worker
    that has served the model and camera before has them."""
    from worker.align.estimator import estimate
    from worker.engine.exceptions import ProxposeError

    request = case.request.model_copy(update={"options": spec.options()})
    start = time.perf_counter()
    try:
        estimate(model, reference, request)
    except ProxposeError:
        pass  # the warm-up only has to build the renderers
    return {"model_path": model_path, "method": spec.label, "seconds": _elapsed(start)}


def _elapsed(start: float) -> float:
    return round(time.perf_counter() - start, 4)


def _case_fields(task: CaseTask, case: Case) -> dict[str, Any]:
    R0, t0 = pose_from_schema(case.request.initial_pose)
    offset_t = translation_error(case.t_true, t0)
    return {
        "case_id": task.case_id,
        "model": task.model,
        "model_path": task.model_path,
        "band": task.band,
        "reference": task.reference,
        "index": task.index,
        "size": task.size,
        "width_px": task.width_px,
        "height_px": task.height_px,
        "initial_rotation_deg": rotation_error_deg(case.R_true, R0),
        "initial_translation_pct": 100.0 * offset_t / float(np.linalg.norm(case.t_true)),
        "initial_speed_score": speed_score(case.R_true, case.t_true, R0, t0),
    }


def run_method(
    model: LoadedModel,
    reference: np.ndarray,
    case: Case,
    spec: MethodSpec,
    est_seed: int,
    fields: dict[str, Any],
    reseed: int = 0,
) -> dict[str, Any]:
    """One timed estimate (with the estimator seed moved on by ``reseed``); an engine error
    (or a crash) is recorded as a failed case."""
    from worker.align.estimator import estimate
    from worker.engine.exceptions import ProxposeError

    seed = (spec.overrides.get("seed", est_seed) + reseed) % 2**31
    request = case.request.model_copy(update={"options": spec.options(seed=seed)})
    record: dict[str, Any] = {**fields, "method": spec.label, "estimator_seed": seed}
    record["seed_index"] = reseed
    reset_peak_memory()
    resident = resident_memory_mb()
    start = time.perf_counter()
    try:
        result = estimate(model, reference, request).result
    except ProxposeError as exc:
        return {**record, **failure(exc.code, exc), "seconds": _elapsed(start)}
    except Exception as exc:  # a bug in one method must not end a long run; it is reported
        log.exception("method %s crashed on case %s", spec.label, fields["case_id"])
        return {**record, **failure("crash", exc), "seconds": _elapsed(start)}
    seconds = _elapsed(start)
    costs = {
        "seconds": seconds,
        "render_equivalents": seconds / fields["render_s"] if fields.get("render_s") else None,
        "peak_memory_mb": (peak := peak_memory_mb()),
        "memory_rise_mb": peak - resident if peak is not None and resident is not None else None,
    }
    return {**record, **outcome(result, case.R_true, case.t_true), **costs}
