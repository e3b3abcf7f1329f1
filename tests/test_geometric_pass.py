"""The geometric pass (worker/align/geometric.py) on a view where the learned rows stop short.

The demo satellite seen with its solar wings nearly in the image plane: a reference ray traced by
the bench's own renderer (worker.bench.raytrace: its supersampling, unfiltered texture, the
exact sun), the estimate started at the true pose. The learned-Jacobian passes walk off along
the weakly seen direction (an out-of-plane rotation against a lateral shift) and stop there,
"converged"; the geometric pass brings the pose back. A pass whose pose the features fit worse
is undone: the estimate is then exactly the learned passes' one.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from schemas import EstimateOptions, EstimateRequest, Lighting
from worker.align import geometric
from worker.align.estimator import estimate
from worker.bench.cases import bench_camera
from worker.bench.references import ReferenceClass, render_class_reference
from worker.bench.synth import CaseSpec, draw_sun, draw_truth, pose_json
from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel
from worker.engine.metrics import rotation_error_deg
from worker.engine.posemath import axis_angle_to_matrix, pose_from_schema

SIZE_PX = 512
#: A view of the demo satellite whose learned passes stop short of the truth (measured
#: 2026-12-03 with estimator seed 2: 1.25° without the pass, 0.25° with it).
VIEW_SEED = 102
#: The estimator seed of the view's request.
VIEW_ESTIMATOR_SEED = 2
#: The bench's ray tracer with its default physics, the true sun, an sRGB 8-bit camera.
EXACT = ReferenceClass("exact", "the ray tracer's default physics, the true sun", False)


@pytest.fixture(scope="module")
def view(demo_model: LoadedModel) -> tuple[np.ndarray, EstimateRequest, np.ndarray]:
    """(reference, request started at the truth, true R)."""
    camera = bench_camera(SIZE_PX)
    cam = PinholeCamera.from_schema(camera)
    rng = np.random.default_rng(VIEW_SEED)
    R, t = draw_truth(demo_model, cam, CaseSpec(3.0, 0.02), rng)
    sun = draw_sun(rng)
    u8 = render_class_reference(demo_model, cam, R, t, sun, EXACT, rng)
    request = EstimateRequest(
        camera=camera,
        initial_pose=pose_json(R, t),
        lighting=Lighting(sun_direction=[float(v) for v in sun]),
        options=EstimateOptions(seed=VIEW_ESTIMATOR_SEED),
    )
    return u8.astype(np.float32) / 255.0, request, R


def _run(model: LoadedModel, view: tuple, geometric_pass: bool):  # noqa: ANN202
    reference, request, R_true = view
    options = request.options.model_copy(update={"geometric_pass": geometric_pass})
    result = estimate(model, reference, request.model_copy(update={"options": options})).result
    assert result.converged, result.reason
    R, _ = pose_from_schema(result.pose)
    return result, rotation_error_deg(R_true, R)


def _seeded(view: tuple, seed: int) -> tuple:
    reference, request, R_true = view
    options = request.options.model_copy(update={"seed": seed})
    return reference, request.model_copy(update={"options": options}), R_true


@pytest.fixture(scope="module")
def learned_run(demo_model: LoadedModel, view: tuple) -> Callable[[int], tuple]:
    """The learned passes' estimate (no geometric pass) of the view with an estimator seed,
    run once per seed in the module (the pass never runs there, so no test's patch of it
    changes it)."""
    runs: dict[int, tuple] = {}

    def run(seed: int) -> tuple:
        if seed not in runs:
            runs[seed] = _run(demo_model, _seeded(view, seed), geometric_pass=False)
        return runs[seed]

    return run


def test_the_geometric_pass_brings_a_stalled_estimate_back(
    demo_model: LoadedModel, view: tuple, learned_run: Callable[[int], tuple]
) -> None:
    # Where the learned passes stop depends on the estimator's seed and on the CPU's render
    # noise (seed 2: 1.25° → 0.25° on one VM, 0.49° → 0.35° on another): medians over three
    # seeds (measured 2026-12-04: learned 0.62°, 0.30°, 0.49°; with the pass 0.13°, 0.10°, 0.35°)
    learned, checked = [], []
    for seed in (0, 1, 2):
        without, error_learned = learned_run(seed)
        with_pass, error_checked = _run(demo_model, _seeded(view, seed), geometric_pass=True)
        assert with_pass.renders > without.renders  # its trial renders
        learned.append(error_learned)
        checked.append(error_checked)
    # (bounds, not the measured values; on an Intel Xeon 2026-12-05: learned 0.58°, 0.29°,
    # 0.47°, with the pass 0.22°, 0.08°, 0.35°, a median 0.47 of the learned one; with the tone
    # curve fitted against the blurred render 0.56°, 0.38°, 0.44° and 0.24°, 0.09°, 0.34°: 0.54)
    assert np.median(learned) > 0.3, learned
    assert np.median(checked) < 0.6 * np.median(learned), (learned, checked)
    assert np.median(checked) < 0.3, checked


def test_a_pass_the_features_fit_worse_is_undone(
    demo_model: LoadedModel,
    view: tuple,
    monkeypatch: pytest.MonkeyPatch,
    learned_run: Callable[[int], tuple],
) -> None:
    learned, _ = learned_run(VIEW_ESTIMATOR_SEED)
    monkeypatch.setattr(geometric, "misfits", lambda features, a, b: (1.0, 0.5, 100))
    undone, _ = _run(demo_model, view, geometric_pass=True)
    assert undone.pose == learned.pose
    assert undone.covariance == learned.covariance
    assert undone.renders > learned.renders
    # How it is undone, from a start the pass surely moves from: the learned passes' session
    # turned 0.3°, its features measured again there (from the learned pose itself, on an AMD
    # EPYC VM the pass accepted no step: nothing to undo, and the history had no way back).
    # The way back is the history's last record, accepted, to where the pass began.
    reference, request, _ = view
    options = request.options.model_copy(update={"geometric_pass": False})
    s = estimate(demo_model, reference, request.model_copy(update={"options": options})).session
    assert s is not None
    s.options = s.options.model_copy(update={"max_iterations": len(s.history) + 10})
    s.R = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.radians(0.3)) @ s.R
    start, fit, stage, records = s.current_view(), s.fit, s.last_stage, len(s.history)
    stage.h, ok = stage.features.measure(start, None)  # where the features are seen from there
    stage.ok = stage.ok & ok
    kept, _ = geometric.run_geometric_pass(s)
    assert not kept
    assert any(r.accepted for r in s.history[records:-1])  # the pass moved
    assert s.current is start and s.fit is fit and s.last_stage is stage
    back = s.history[-1]
    assert back.accepted and back.step_norm > 0
    np.testing.assert_allclose(back.pose.R, start.R)


def test_too_few_geometric_rows_leave_the_learned_pose(
    demo_model: LoadedModel,
    view: tuple,
    monkeypatch: pytest.MonkeyPatch,
    learned_run: Callable[[int], tuple],
) -> None:
    # (e.g. most features on the silhouette against the sky, where a ray hits nothing)
    from worker.engine.exceptions import TooFewFeaturesError

    learned, _ = learned_run(VIEW_ESTIMATOR_SEED)

    def too_few(*args: object, **kwargs: object) -> None:
        raise TooFewFeaturesError("only 3 features usable (need 6)")

    monkeypatch.setattr(geometric, "run_lm_stage", too_few)
    result, _ = _run(demo_model, view, geometric_pass=True)
    assert result.pose == learned.pose and result.covariance == learned.covariance


@pytest.mark.parametrize(
    ("turns", "learned_passes"),
    [
        ([0.02], 0),  # a small move: the learned passes had converged
        ([0.5, 0.01], 1),  # a large one: one more learned pass, then the pass again
        ([0.5, 0.4, 0.3], 2),  # at most MAX_RECHECKS more learned passes
        ([0.5, None], 1),  # the pass after the extra learned one is undone
    ],
)
def test_a_large_geometric_move_earns_another_learned_pass(
    monkeypatch: pytest.MonkeyPatch, turns: list[float | None], learned_passes: int
) -> None:
    # (narrow: the passes are fakes; the view above runs the real ones)
    from types import SimpleNamespace

    from worker.engine.posemath import axis_angle_to_matrix

    moves = iter(turns)

    def fake_pass(session: SimpleNamespace) -> tuple[bool, str | None]:
        turn = next(moves)
        if turn is None:
            return False, "cost_converged"
        session.R = session.R @ axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.radians(turn))
        return True, "step_below_epsilon"

    calls: list[str] = []
    monkeypatch.setattr(geometric, "run_geometric_pass", fake_pass)
    session = SimpleNamespace(
        R=np.eye(3), options=EstimateOptions(geometric_recheck_deg=0.15), iterations_left=10
    )
    outcome = geometric.geometric_passes(
        session,  # type: ignore[arg-type]
        lambda: calls.append("learned") or "slow",
        "slow",
    )
    assert len(calls) == learned_passes
    # the stop rule of the last pass that moved the pose: a kept geometric pass's own
    assert outcome == ("slow" if turns[-1] is None else "step_below_epsilon")
    assert geometric.MAX_RECHECKS == 2
