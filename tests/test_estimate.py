"""Full estimates on small renders (worker/align/estimator.py through worker/entry.py).

References come from worker.bench.synth: rendered with another renderer setup (path tracing,
Gaussian filter, gamma 2.2, exposure change, sun 3° off, noise, 8 bits) at a known pose; the
initial guess is 3° and 3 % of the range away. One estimate per method is shared by the tests
that read it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import shared_model

from schemas.camera import Camera
from schemas.estimate import EstimateRequest, EstimateResult, IterationRecord
from schemas.options import EstimateOptions
from schemas.pose import Pose
from schemas.render import RenderRequest
from worker.align.artifacts import ARTIFACT_NAMES
from worker.bench.synth import Case, CaseSpec, make_case
from worker.engine.exceptions import (
    EmptyRenderError,
    EstimationCancelled,
    ImageSizeMismatchError,
    TooFewFeaturesError,
)
from worker.engine.images import decode_image, encode_png
from worker.engine.meshes import LoadedModel, load_model

pytestmark = pytest.mark.slow

SIZE_PX = 256
#: The demo satellite spans 16 units of solar array around a 2-unit bus: frame the array
#: edge to edge so that the bus is resolved.
DEMO_SPEC = CaseSpec(offset_deg=3.0, offset_frac=0.03, fill=1.0)
#: Accuracy required of the default method (issue 2).
MAX_ROTATION_DEG = 0.3
MAX_TRANSLATION_PCT = 0.5


def _camera(size: int) -> Camera:
    return Camera(width=size, height=size, fx=1.17 * size, fy=1.17 * size,
                  cx=size / 2 - 0.5, cy=size / 2 - 0.5)  # fmt: skip


def _with_options(case: Case, **options: object) -> EstimateRequest:
    return case.request.model_copy(update={"options": EstimateOptions(**options)})


def _run(path: Path, case: Case, request: EstimateRequest | None = None, **kw: object):  # noqa: ANN202
    from worker.entry import run_estimate

    return run_estimate(path, encode_png(case.reference), request or case.request, **kw)


@pytest.fixture(scope="module")
def demo_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from worker.demo.satellite import demo_satellite_path

    return demo_satellite_path(tmp_path_factory.mktemp("demo"))


@pytest.fixture(scope="module")
def demo_model(demo_path: Path) -> LoadedModel:
    return load_model(demo_path)


@pytest.fixture(scope="module")
def demo_case(demo_model: LoadedModel, variant: str) -> Case:
    return make_case(demo_model, _camera(SIZE_PX), DEMO_SPEC, seed=0)


@pytest.fixture(scope="module")
def default_run(demo_path: Path, demo_case: Case) -> tuple[EstimateResult, dict[str, bytes]]:
    return _run(demo_path, demo_case)


# -- the default method -------------------------------------------------------------------
def test_default_estimate_is_accurate(default_run: tuple[EstimateResult, dict]) -> None:
    result, _ = default_run
    assert result.initial_errors is not None and result.errors is not None
    assert result.initial_errors.rotation_deg == pytest.approx(3.0, abs=1e-6)
    assert result.initial_errors.translation_pct_of_range == pytest.approx(3.0, abs=1e-6)
    assert result.converged, result.reason
    assert result.errors.rotation_deg < MAX_ROTATION_DEG
    assert result.errors.translation_pct_of_range < MAX_TRANSLATION_PCT


def test_default_estimate_fills_the_result(
    default_run: tuple[EstimateResult, dict], demo_case: Case, variant: str
) -> None:
    result, _ = default_run
    assert result.method == "default" and result.variant == variant
    hist = result.history
    assert result.iterations == len(hist) >= 2
    assert [h.iteration for h in hist] == list(range(1, len(hist) + 1))
    assert hist[0].stage == "coarse" and hist[-1].stage == "refine"  # PnP, then the LM
    assert all(h.renders >= 0 and h.features >= 0 and h.rotation_error_deg is not None
               for h in hist)  # fmt: skip
    # Each refinement pass learns its Jacobian once (N_s perturbed renders), then reuses it.
    opts = demo_case.request.options.resolved()
    learning = [h for h in hist if h.stage == "refine" and h.renders > opts.n_samples]
    assert len(learning) == opts.refine_passes == 2
    assert result.renders >= sum(h.renders for h in hist) > 0
    assert result.features >= 6 and result.rms_residual_px > 0
    assert result.timings_s["render"] > 0
    # The last accepted iteration's pose is the result.
    last = [h for h in hist if h.accepted][-1]
    np.testing.assert_allclose(last.pose.R, result.pose.R, atol=1e-12)
    cov = result.covariance
    assert cov is not None
    C = np.array(cov.matrix)
    np.testing.assert_allclose(C, C.T, atol=1e-12 * np.abs(C).max())
    assert (np.linalg.eigvalsh(C) > 0).all()
    assert all(0 < s < 1.0 for s in cov.sigma_rotation_deg)  # degrees, plausible
    assert all(0 < s < 0.05 * np.linalg.norm(demo_case.t_true) for s in cov.sigma_translation)


def _angle_deg(a: object, b: object) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def test_default_estimate_fits_the_sun(
    default_run: tuple[EstimateResult, dict], demo_case: Case
) -> None:
    """The request's sun is 3° off the reference's; the fitted one is closer to it."""
    result, _ = default_run
    asked = demo_case.request.lighting.sun_direction
    assert _angle_deg(asked, demo_case.sun_true) == pytest.approx(3.0, abs=1e-6)
    assert result.sun_direction is not None
    assert np.linalg.norm(result.sun_direction) == pytest.approx(1.0)
    assert result.sun_tilt_deg == pytest.approx(_angle_deg(asked, result.sun_direction), abs=1e-6)
    assert 0.5 < result.sun_tilt_deg <= 10.0
    assert _angle_deg(result.sun_direction, demo_case.sun_true) < 2.0


def test_sun_fit_off_keeps_the_requested_sun(demo_path: Path, demo_case: Case) -> None:
    result, _ = _run(
        demo_path, demo_case, _with_options(demo_case, fit_sun=False), with_artifacts=False
    )
    assert result.sun_tilt_deg == 0.0
    np.testing.assert_allclose(result.sun_direction, demo_case.request.lighting.sun_direction)


def test_a_pass_whose_steps_do_not_shrink_is_followed_by_a_fresh_one(demo_path: Path) -> None:
    """A small (128 px) view where the first pass's Jacobian overstates the motion: its steps
    stay the same size (0.6° → 0.49° in four steps). The pass ends 'slow' and a new one, with a
    Jacobian learned where it stopped, converges, even when one pass was asked for."""
    from e2e_helpers import R_TRUE, T_TRUE, camera, initial_pose, pose

    from worker.entry import render_png, run_estimate

    truth = pose(R_TRUE, T_TRUE)
    render = RenderRequest.model_validate({"camera": camera(128), "pose": truth, "spp": 32})
    reference = render_png(demo_path, render)
    for passes in (1, 2):
        request = EstimateRequest.model_validate({
            "camera": camera(128),
            "initial_pose": initial_pose(),
            "ground_truth": truth,
            "options": {"spp": 128, "perturbation_spp": 32, "refine_passes": passes},
        })  # fmt: skip
        result, _ = run_estimate(demo_path, reference, request, with_artifacts=False)
        learning = [h for h in result.history if h.stage == "refine" and h.renders > 12]
        assert len(learning) >= 2, passes
        assert result.converged, (passes, result.reason)
        assert result.errors is not None and result.errors.rotation_deg < 0.2, passes


def test_an_attitude_search_brings_a_start_12_degrees_off_within_reach(
    demo_path: Path, demo_model: LoadedModel, variant: str
) -> None:
    """options.attitude_search (a tracker's lost frame after a jump): its first record is the
    search's, which turns the target about its centre from 12° off to within a few degrees, in
    158 renders at the coarse level; the estimate then converges. Without it the first record
    is the moment alignment's, and the attitude is as far off as it started."""
    case = make_case(demo_model, _camera(SIZE_PX), CaseSpec(12.0, 0.0, fill=1.0), seed=3)
    searched, _ = _run(demo_path, case, _with_options(case, attitude_search=True),
                       with_artifacts=False)  # fmt: skip
    first = searched.history[0]
    assert first.stage == "coarse" and first.accepted and first.renders >= 158
    assert first.rotation_error_deg is not None and first.rotation_error_deg < 4.0
    assert searched.converged, searched.reason
    assert searched.errors is not None and searched.errors.rotation_deg < MAX_ROTATION_DEG
    plain, _ = _run(demo_path, case, with_artifacts=False)
    assert plain.history[0].rotation_error_deg == pytest.approx(12.0, abs=0.5)
    assert plain.history[0].renders < 10


def test_artifacts_are_pngs_of_the_image_size(default_run: tuple[EstimateResult, dict]) -> None:
    result, artifacts = default_run
    assert set(artifacts) == set(ARTIFACT_NAMES) == set(result.artifacts)
    for name, png in artifacts.items():
        assert png.startswith(b"\x89PNG\r\n\x1a\n"), name
        img = decode_image(png)
        if name == "convergence":
            assert img.ndim == 3 and min(img.shape[:2]) >= 200
        else:
            assert img.shape[:2] == (SIZE_PX, SIZE_PX), name
        assert img.std() > 0.01, f"{name} is blank"


# -- the other methods --------------------------------------------------------------------
def test_pnp_method(demo_path: Path, demo_case: Case) -> None:
    result, _ = _run(demo_path, demo_case, _with_options(demo_case, method="pnp"))
    assert result.method == "pnp"
    assert {h.stage for h in result.history} == {"coarse"}
    assert all(h.lambda_ == 0.0 for h in result.history)
    # one render per PnP step, the judge of the last one when the iterations run out, the final
    assert result.renders <= result.iterations + 2
    assert result.errors.rotation_deg < 2.0
    assert result.errors.translation_pct_of_range < 2.0


@pytest.mark.xfail(
    strict=True,
    raises=TooFewFeaturesError,
    reason="the paper's configuration, read literally, fails on this small target: of its 4 "
    "matched features (the most trackable of the matches), one is lost in some of the 24 "
    "perturbed renders even after 3 shrinking resamplings, and features lost in any view are "
    "dropped (jacobian='common'); the default method's per-feature rows avoid exactly this",
)
def test_paper_method(demo_path: Path, demo_case: Case) -> None:
    """The paper read literally: 4 matched features, 24 full-size perturbation renders per
    iteration, no PnP. Three iterations (~90 renders) keep the test affordable."""
    request = _with_options(demo_case, method="paper", max_iterations=3)
    result, _ = _run(demo_path, demo_case, request, with_artifacts=False)
    assert result.method == "paper"
    assert {h.stage for h in result.history} == {"refine"}
    assert result.iterations == 3
    assert result.renders > 3 * 24  # the Jacobian is learned afresh at every pose
    assert all(h.features <= 4 for h in result.history)
    assert result.errors.rotation_deg < 2.0
    assert result.errors.translation_pct_of_range < 2.0


def test_paper_method_does_not_walk_away(demo_path: Path, demo_model: LoadedModel) -> None:
    """Every accepted step is judged on at least min_features features (a 6-DoF step checked
    on fewer is unconstrained), so the estimate never ends farther from the truth than it
    started (it used to jump from 2.2° to 18° on a step judged on 1 of 4 features)."""
    case = make_case(demo_model, _camera(SIZE_PX), DEMO_SPEC, seed=2)
    request = _with_options(case, method="paper", max_iterations=3)
    result, _ = _run(demo_path, case, request, with_artifacts=False)
    assert all(h.features >= 4 for h in result.history if h.accepted)
    assert result.errors.rotation_deg <= result.initial_errors.rotation_deg + 1e-9


# -- callbacks and errors -----------------------------------------------------------------
def test_progress_callback_and_cancellation(demo_path: Path, demo_case: Case) -> None:
    request = _with_options(demo_case, method="pnp")
    seen: list[tuple[IterationRecord, int]] = []
    result, _ = _run(demo_path, demo_case, request, with_artifacts=False,
                     on_iteration=lambda rec, n: seen.append((rec, n)))  # fmt: skip
    assert [rec for rec, _ in seen] == result.history
    assert {n for _, n in seen} == {request.options.max_iterations}

    calls: list[int] = []

    def cancel_after_first_iteration() -> bool:
        calls.append(1)
        return len(seen_again) >= 1

    seen_again: list[IterationRecord] = []
    with pytest.raises(EstimationCancelled):
        _run(demo_path, demo_case, request, with_artifacts=False,
             on_iteration=lambda rec, n: seen_again.append(rec),
             should_cancel=cancel_after_first_iteration)  # fmt: skip
    # Checked before each render: the estimate stops within an iteration of the request.
    assert calls and 1 <= len(seen_again) <= 2 < len(seen)


def test_same_request_gives_the_same_result(demo_path: Path, demo_case: Case) -> None:
    """Seeded throughout: a repeated request (warm renderer cache) reproduces the estimate."""
    request = _with_options(demo_case, method="pnp", seed=7)
    first, _ = _run(demo_path, demo_case, request, with_artifacts=False)
    again, _ = _run(demo_path, demo_case, request, with_artifacts=False)
    assert again.pose == first.pose
    assert [h.cost for h in again.history] == [h.cost for h in first.history]


def test_target_out_of_view_is_an_empty_render(demo_model: LoadedModel, demo_case: Case) -> None:
    from worker.align.estimator import estimate

    t = demo_case.request.initial_pose.t
    # Far to the side; far away (the target then covers much less than a pixel).
    for t_bad in ([t[0] + 50 * t[2], t[1], t[2]], [t[0], t[1], 1e5 * t[2]]):
        pose = Pose(t=t_bad, quaternion=demo_case.request.initial_pose.quaternion)
        request = demo_case.request.model_copy(update={"initial_pose": pose})
        with pytest.raises(EmptyRenderError, match="not visible"):
            estimate(demo_model, demo_case.reference / 255.0, request)


def test_image_of_the_wrong_size(demo_model: LoadedModel, demo_case: Case) -> None:
    from worker.align.estimator import estimate

    small = np.zeros((SIZE_PX, SIZE_PX - 1, 3), np.float32)
    with pytest.raises(ImageSizeMismatchError, match=f"{SIZE_PX - 1}×{SIZE_PX} px"):
        estimate(demo_model, small, demo_case.request)


# -- the public models --------------------------------------------------------------------
SHARED_SIZE_PX = 384


@pytest.mark.shared
@pytest.mark.parametrize("name", ["phobos", "aura", "iss"])
def test_estimate_on_a_shared_model(name: str, variant: str) -> None:
    path = shared_model(name)
    case = make_case(load_model(path), _camera(SHARED_SIZE_PX), CaseSpec(3.0, 0.03), seed=0)
    result, _ = _run(path, case, with_artifacts=False)
    assert result.converged, result.reason
    assert result.errors.rotation_deg < MAX_ROTATION_DEG
    assert result.errors.translation_pct_of_range < MAX_TRANSLATION_PCT


@pytest.mark.shared
def test_the_coarse_stage_matches_at_full_size_when_its_level_has_too_few_matches(
    variant: str,
) -> None:
    """Aura (thin booms and one array) at 640 × 480, 10–20° off (a bench case): at the coarse
    level (half size) PnP finds too few descriptor matches. The coarse stage then matches at
    full size; without that the refinement, starting 14° off with 3–7 features, ended 9.6° off
    and called itself converged."""
    from worker.align.estimator import estimate, target_px
    from worker.align.pyramid import plan_levels
    from worker.bench.cases import CaseTask, build_case, parse_method
    from worker.engine.camera import PinholeCamera
    from worker.engine.posemath import pose_from_schema

    path = shared_model("aura")
    model = load_model(path)
    task = CaseTask("aura", str(path), 20.0, 10.0, 0, 640, 480, 0, "uniform",
                    [parse_method("default")])  # fmt: skip
    case, seed = build_case(task, model)
    camera = PinholeCamera.from_schema(case.request.camera)
    guess = target_px(model, camera, *pose_from_schema(case.request.initial_pose))
    assert plan_levels(camera, guess, 0.5, pyramid=True).coarse == 0.5
    request = case.request.model_copy(update={"options": EstimateOptions(seed=seed)})
    result = estimate(model, case.reference.astype(np.float32) / 255.0, request).result
    assert result.converged, result.reason
    assert result.errors is not None and result.errors.rotation_deg < MAX_ROTATION_DEG


def test_when_no_full_size_pass_finds_features_the_coarse_pass_stands(
    demo_model: LoadedModel, variant: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Found on a terrain lit by a sun 1.6° above the horizon (`proxpose bench --terrain
    --sun-elevation 3,12 --cases 4 --seed 5`, started at the truth): the half-size pass ran,
    the full-size one found too few features. The geometric pass then ran the half-size
    pass's features on full-size renders and the estimate crashed (a ValueError of array
    shapes). Now the half-size pass's pose stands, with its fit for the covariance, and the
    geometric pass does not run on its features. Here the full-size passes are made to find
    too few features (the rest is a real estimate); a spy records any geometric pass."""
    from worker.align import estimator, geometric

    real_pass, real_stage = estimator._pass, geometric.run_lm_stage
    full_size_calls = []
    geometric_runs = []

    def recorded_stage(session, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        geometric_runs.append(session.level)
        return real_stage(session, *args, **kwargs)

    def no_features_at_full_size(session, fit_sun):  # noqa: ANN001, ANN202
        if session.level == 1.0:
            full_size_calls.append(session.last_stage.level)
            raise TooFewFeaturesError("only 3 features found in common (need 8)")
        return real_pass(session, fit_sun)

    monkeypatch.setattr(estimator, "_pass", no_features_at_full_size)
    monkeypatch.setattr(geometric, "run_lm_stage", recorded_stage)
    case = make_case(demo_model, _camera(2 * SIZE_PX), DEMO_SPEC, seed=0)  # a half-size pass
    result = estimator.estimate(
        demo_model, case.reference.astype(np.float32) / 255.0, case.request
    ).result
    assert full_size_calls == [0.5], "no full-size pass after a half-size one"
    assert geometric_runs == [], "the geometric pass ran on the half-size pass's features"
    refine = [h for h in result.history if h.stage == "refine"]
    assert refine and all(h.stage == "refine" for h in result.history[-len(refine) :])
    assert result.covariance is not None
    # a half-size pass's pose: 0.32° off here (the full-size passes end 0.035° off)
    assert result.errors is not None and result.errors.rotation_deg < 1.0
