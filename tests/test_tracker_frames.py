"""A tracked frame's session (worker/align/tracker.py), no Mitsuba: what it inherits from the
previous frame's and what it sets for itself."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from test_refine import R0, T0, K, linear_problem, make_session  # noqa: F401 (a fixture)

from schemas.camera import Camera
from schemas.estimate import EstimateRequest
from schemas.options import EstimateOptions
from schemas.pose import Pose
from worker.align.refine import StageState, run_lm_stage
from worker.align.session import Session
from worker.align.tracker import (
    FRAME_ITERATIONS,
    MIN_KEPT_FRACTION,
    MIN_TRACKED_FRACTION,
    TRACK_PERTURBATION_SPP,
    VELOCITY_FRAMES,
    FrameResult,
    Tracker,
)
from worker.align.trackmemory import Memory, mispredicted
from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.metrics import rotation_error_deg
from worker.engine.posemath import axis_angle_to_matrix


def _tracked_session(
    perturbation_spp: int, sun: tuple[float, float, float] | None = None
) -> tuple[Session, list[int]]:
    """A tracked frame's session after a previous frame's with ``perturbation_spp`` (that left
    the renderer's sun tilted to ``sun``), and the samples per pixel of each render it makes."""
    previous = make_session(perturbation_spp=perturbation_spp)
    requested = previous.requested_lighting
    if sun is not None:
        previous.renderer.set_lighting(replace(requested, sun_direction=sun))
    spps: list[int] = []
    render = previous.renderer.render

    def counted(*args: object, **kwargs: object) -> np.ndarray:
        spps.append(int(kwargs["spp"]))  # type: ignore[call-overload]
        return render(*args, **kwargs)  # type: ignore[arg-type]

    previous.renderer.render = counted  # type: ignore[method-assign]
    tracker = Tracker.__new__(Tracker)
    tracker.should_cancel = None
    tracker._points = np.zeros((1, 3), np.float32)  # the stub renderer has no window sensors
    tracker._requested = requested
    image = np.zeros((64, 64, 3), np.float32)
    return tracker._session(previous, image, (R0, T0), None), spps


def test_a_tracked_frame_learns_from_perturbations_with_the_tracker_spp() -> None:
    session, spps = _tracked_session(perturbation_spp=4)
    assert session.options.perturbation_spp == TRACK_PERTURBATION_SPP
    assert session.options.max_iterations == FRAME_ITERATIONS
    session.render_perturbed(R0, T0, seed=1)
    assert spps == [TRACK_PERTURBATION_SPP]


def test_a_tracked_frame_s_sun_prior_is_the_request_s_not_the_last_fit() -> None:
    """The renderer keeps the sun the last fit tilted; a frame that solves for the sun again
    pulls it towards the request's, not towards that fit."""
    tilted = (0.1, -0.6, -0.79)
    session, _ = _tracked_session(perturbation_spp=4, sun=tilted)
    assert session.renderer.lighting.sun_direction == tilted
    assert session.requested_lighting.sun_direction == (0.0, -0.6, -0.8)


def test_more_samples_asked_for_are_kept() -> None:
    session, _ = _tracked_session(perturbation_spp=4 * TRACK_PERTURBATION_SPP)
    assert session.options.perturbation_spp == 4 * TRACK_PERTURBATION_SPP


def _request(options: EstimateOptions | None = None) -> EstimateRequest:
    """A 64-px track request whose first guess is (I, T0)."""
    camera = Camera(width=64, height=64, fx=60.0, fy=60.0, cx=31.5, cy=31.5)
    initial = Pose(t=list(map(float, T0)), quaternion=[1.0, 0.0, 0.0, 0.0])
    options = options or EstimateOptions()
    return EstimateRequest(camera=camera, initial_pose=initial, options=options)


def _scripted_tracker(frames: list[tuple[str, float]]) -> Tracker:
    """A tracker whose frames come out as scripted: (status, attitude about z in deg); the
    velocity logic of Tracker.track is what runs."""
    script = iter(frames)

    def next_frame(*args: object) -> FrameResult:
        status, deg = next(script)
        R = axis_angle_to_matrix([0.0, 0.0, 1.0], np.radians(deg))
        return FrameResult(0, R, T0, status, status != "lost", 0.0, 1, 0.1, 0.99, 50)

    tracker = Tracker.__new__(Tracker)
    tracker.request = _request()
    tracker.poses, tracker._motions, tracker._misalignment = [], [], []
    tracker._last_full = False
    tracker._memory = None  # every frame goes through _full, scripted
    tracker._full = next_frame  # type: ignore[method-assign]
    image = np.zeros((64, 64), np.float32)
    for _ in frames:
        tracker.track(image)
    return tracker


def _predicted_deg(tracker: Tracker) -> float:
    return rotation_error_deg(np.eye(3), tracker.predicted()[0])


def test_the_first_motion_is_a_velocity_even_into_a_re_initialised_frame() -> None:
    # frame 1 was lost by the tracker and re-initialised: its motion is all there is to go on
    tracker = _scripted_tracker([("reinitialised", 0.0), ("reinitialised", 2.0)])
    np.testing.assert_allclose(_predicted_deg(tracker), 4.0, atol=1e-6)


def test_a_jump_is_not_a_velocity() -> None:
    # the first motion too large to be one: the next frame starts where the last ended
    tracker = _scripted_tracker([("reinitialised", 0.0), ("reinitialised", 12.0)])
    np.testing.assert_allclose(_predicted_deg(tracker), 12.0, atol=1e-6)
    # once tracked frames give a velocity, a re-initialised frame's motion does not replace it
    tracker = _scripted_tracker(
        [("reinitialised", 0.0), ("tracked", 1.0), ("tracked", 2.0), ("reinitialised", 5.0)]
    )
    np.testing.assert_allclose(_predicted_deg(tracker), 6.0, atol=1e-6)


def test_the_velocity_is_the_mean_of_the_last_motions() -> None:
    # a frame left 0.3° along: the next start is carried 0.1° on by it, not 0.3°
    tracker = _scripted_tracker(
        [("reinitialised", 0.0), ("tracked", 1.0), ("tracked", 2.0), ("tracked", 3.3)]
    )
    assert VELOCITY_FRAMES == 3
    np.testing.assert_allclose(_predicted_deg(tracker), 3.3 + 1.1, atol=1e-4)
    # only the last VELOCITY_FRAMES motions count: the first, slower one is gone
    tracker = _scripted_tracker(
        [
            ("reinitialised", 0.0),
            ("tracked", 0.5),
            ("tracked", 1.5),
            ("tracked", 2.5),
            ("tracked", 3.5),
        ]
    )
    np.testing.assert_allclose(_predicted_deg(tracker), 4.5, atol=1e-4)


def test_a_frame_that_lost_half_its_features_learns_again_instead_of_being_lost() -> None:
    # converged and aligned: fewer than MIN_KEPT_FRACTION of the learned features make the
    # frame learn afresh (Tracker._keep), only fewer than MIN_TRACKED_FRACTION make it lost
    tracker = Tracker.__new__(Tracker)
    tracker._misalignment = [0.004] * 5
    assert MIN_TRACKED_FRACTION < MIN_KEPT_FRACTION
    assert not tracker._lost("linear_step", 0.995, 40, 100)
    assert not tracker._lost("cost_converged", 0.995, 26, 100)
    assert tracker._lost("cost_converged", 0.995, 24, 100)
    # the other rules stand: a stop rule that is no convergence, a poor or a jumping score
    assert tracker._lost("max_iterations", 0.995, 100, 100)
    assert tracker._lost("linear_step", 0.80, 100, 100)
    assert tracker._lost("linear_step", 0.98, 100, 100)  # 5 × the last frames' misalignment


def test_a_trial_the_rows_mispredict_is_told_from_a_stop_without_one(
    linear_problem: list[np.ndarray],  # noqa: F811 (the fixture imported above)
) -> None:
    """The real stage on an exactly linear problem: with the right rows every trial is accepted
    and the stage stops without one (a record unaccepted, but with its step); with rows of the
    wrong sign the first trial raises the cost and is rejected (unaccepted, no step)."""
    session = make_session()
    run_lm_stage(session, "klt", "refine")
    assert session.history[-1].accepted is False and session.history[-1].step_norm > 0.0
    assert not mispredicted(session)
    linear_problem[0] = np.array(-1.0)
    session = make_session()
    run_lm_stage(session, "klt", "refine")
    assert any(r.step_norm == 0.0 and not r.accepted for r in session.history)
    assert mispredicted(session)


def test_a_frame_whose_rows_mispredicted_a_trial_learns_them_afresh() -> None:
    """Tracker._keep: a frame that neither turned far nor lost features keeps its rows, unless
    its LM rejected a trial; then it learns rows and features afresh (the fresh set stubbed:
    learning it is the real tracker's, tests/test_tracker.py)."""
    ok = np.ones(K, dtype=bool)
    carried = StageState(SimpleNamespace(smeared=False), np.zeros((K, 2)), ok)  # type: ignore[arg-type]
    fresh = StageState(SimpleNamespace(smeared=False), np.zeros((K, 2)), ok)  # type: ignore[arg-type]
    tracker = Tracker.__new__(Tracker)
    tracker._fresh = lambda session: fresh  # type: ignore[method-assign]
    for rejected in (False, True):
        session = make_session()  # fit_sun off: no sun fit after learning afresh
        session.last_stage = carried
        session.record("refine", 0.01, 1e-4, 1e-3, True, K)  # an accepted trial
        if rejected:
            session.record("refine", 0.01, 0.0, 1e-2, False, K)
        memory = Memory(carried, (R0, T0), K, session)
        assert tracker._keep(session, memory, K) is rejected
        assert tracker._memory is not None
        assert tracker._memory.state is (fresh if rejected else carried)


def test_a_jump_a_tracked_frame_caught_is_not_a_velocity() -> None:
    # frame 3 ended 12° past its prediction (a jump caught by learning afresh): the velocity
    # stays the frames' 1° a frame, instead of a mean with the jump in it (5° a frame)
    tracker = _scripted_tracker(
        [("reinitialised", 0.0), ("tracked", 1.0), ("tracked", 2.0), ("tracked", 15.0)]
    )
    np.testing.assert_allclose(_predicted_deg(tracker), 16.0, atol=1e-4)


def test_two_full_estimates_in_a_row_start_the_velocity_again() -> None:
    # a jump (frame 3, re-initialised) and another full estimate: the motion between the two
    # is the velocity now, not the one from before the jump
    tracker = _scripted_tracker(
        [
            ("reinitialised", 0.0),
            ("tracked", 1.0),
            ("tracked", 2.0),
            ("reinitialised", 20.0),
            ("reinitialised", 23.0),
        ]
    )
    np.testing.assert_allclose(_predicted_deg(tracker), 26.0, atol=1e-4)
    # unless that motion is a jump too
    tracker = _scripted_tracker(
        [("reinitialised", 0.0), ("tracked", 1.0), ("reinitialised", 20.0), ("reinitialised", 40.0)]
    )
    np.testing.assert_allclose(_predicted_deg(tracker), 41.0, atol=1e-4)


@pytest.mark.parametrize(
    ("asked", "first", "second", "calls", "status"),
    [
        (False, True, None, [False], "reinitialised"),
        (False, None, True, [False, True], "reinitialised"),  # TooFewFeaturesError, converged
        (False, False, True, [False, True], "reinitialised"),
        (False, False, None, [False, True], "lost"),
        (False, False, 0.75, [False, True], "lost"),  # converged, aligned poorly: a wrong attitude
        (True, None, True, [False], "lost"),  # the first searched already: not the same again
    ],
)
def test_a_lost_frame_searches_its_attitude_when_the_estimate_from_the_prediction_fails(
    asked: bool, first: bool | None, second: bool | float | None, calls: list[bool], status: str
) -> None:
    """Tracker._recover with its full estimates scripted (the search is the engine's, real in
    tests/test_estimate.py): a full estimate from the guess; when that raises (None) or does not
    converge, one with options.attitude_search, kept when it converged and its render aligns as
    a tracked frame's must (a float: its alignment score, else 0.99); else the frame is lost.
    When the track's request ``asked`` for the search, the first estimate searched (Tracker._full)
    and there is no second."""
    guess = (axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.radians(12.0)), np.ones(3))
    made: list[bool] = []

    def full(*args: object) -> FrameResult:
        search = bool(args[6])
        made.append(search)
        converged = second if search else first
        if converged is None:
            raise TooFewFeaturesError("only 5 features usable (need 6)")
        score = converged if isinstance(converged, float) else 0.99
        return FrameResult(3, *guess, "reinitialised", bool(converged), 1.0, 9, 9.0, score, 40)

    tracker = Tracker.__new__(Tracker)
    tracker.request = _request(EstimateOptions(attitude_search=asked))
    tracker._misalignment = [0.004] * 5
    tracker._full = full  # type: ignore[method-assign]
    frame = tracker._recover(np.zeros((8, 8), np.float32), guess, None, 3, 0.0)
    assert (made, frame.status) == (calls, status)
    np.testing.assert_array_equal(frame.R, guess[0])


@pytest.mark.parametrize(
    ("asked", "search", "searched"),
    [(False, False, False), (False, True, True), (True, False, True), (True, True, True)],
)
def test_a_full_estimate_searches_when_the_frame_s_recovery_or_the_request_asks(
    asked: bool, search: bool, searched: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tracker._full's request: attitude_search on for a recovery's second try (``search``) and
    whenever the track's request asked for it (the first frame too); the estimate is stopped at
    its call (the search itself is the engine's, tests/test_estimate.py)."""
    seen: list[EstimateRequest] = []

    def stop(model: object, image: object, request: EstimateRequest, **kw: object) -> None:
        seen.append(request)
        raise TooFewFeaturesError("stopped at the call")

    monkeypatch.setattr("worker.align.tracker.estimate", stop)
    tracker = Tracker.__new__(Tracker)
    tracker.request = _request(EstimateOptions(attitude_search=asked))
    tracker.model, tracker.should_cancel = None, None  # type: ignore[assignment]
    with pytest.raises(TooFewFeaturesError):
        tracker._full(np.zeros((64, 64), np.float32), (R0, T0), None, 0, 0.0, "reinitialised",
                      search)  # fmt: skip
    assert seen[0].options.attitude_search is searched
    assert seen[0].initial_pose.t == list(map(float, T0))
