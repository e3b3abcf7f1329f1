"""Tracking an image sequence: each frame goes on from what the previous one learned.

The first frame is a full estimate from the request's initial pose. Every later frame starts
from a constant-velocity prediction and keeps the previous frame's features (each tracked from
the previous image into the new one, starting where the learned Jacobian predicts it moved),
their learned Jacobian rows (Broyden-updated by every accepted step), the fitted sun, the tone
curve and the sharpness match (motion blur's streak measured again); so a frame costs a render
at the prediction, a trial only when the LM's step moves a feature by LINEAR_STEP_PX or more, and
one when its rows disagree with the geometry along a weak direction (worker.align.weakprobe).
The learned-Jacobian LM stays the core: the rows are the paper's, learned again (features made
afresh, the sun's tilt solved again with options.fit_sun) once the attitude has turned
RELEARN_ROTATION_DEG since, too few features are left, or the LM rejected a trial. Its robust
weights keep features a few tenths of a pixel out (TRACK_ROBUST_FLOOR_PX). A frame's renders
render only a window around the target, pasted onto the sky (worker.align.skywindow).

Each frame is refereed: a poor last render (alignment score below MIN_TRACK_SCORE, or far below
the last frames'), too few features (MIN_TRACKED_FRACTION) or an LM that does not converge (after
learning afresh when only still moving, UNFINISHED) mark it lost: a full estimate from where the
LM got to (if aligned) or the prediction re-initialises it, failing that one searching the attitude.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from schemas.estimate import EstimateRequest
from worker.align.estimator import MIN_CONVERGED_SCORE, covariance_of, errors_between, estimate
from worker.align.learning import LearnedJacobian
from worker.align.refine import StageState, run_lm_stage
from worker.align.session import CancelCheck, Session
from worker.align.skywindow import outline_points, sky_window
from worker.align.tracked import TrackedFeatures, inherited_smear, law_misplaced, work_box
from worker.align.trackmemory import Memory, Pose, fresh_state, mispredicted
from worker.align.trackresult import FrameResult
from worker.align.weakprobe import probe_weak_directions
from worker.engine.exceptions import ProxposeError, TooFewFeaturesError
from worker.engine.images import FloatImage, check_size, to_grey
from worker.engine.meshes import LoadedModel
from worker.engine.metrics import rotation_error_deg
from worker.engine.photometry import alignment_score
from worker.engine.posemath import (
    apply_increment,
    increment_between,
    pose_from_schema,
    pose_to_schema,
)
from worker.engine.renderer import LightingSpec

Array = NDArray[np.float64]

#: Iterations (trials) a tracked frame may take.
FRAME_ITERATIONS = 4
#: Alignment score below which a tracked frame is taken as lost.
MIN_TRACK_SCORE = 0.85
#: A frame is lost, too, when its misalignment (1 − alignment score) exceeds this many times
#: the median of the last MISALIGNMENT_FRAMES accepted frames' (and at least
#: MIN_MISALIGNMENT): the score's level depends on the target and the image, its jump does not.
MISALIGNMENT_GROWTH = 3.0
MISALIGNMENT_FRAMES = 5
MIN_MISALIGNMENT = 0.005
#: Fraction of the features learned together that a frame must still fit to go on with them;
#: below it the frame learns its Jacobian afresh, with features made where it converged.
#: Below MIN_TRACKED_FRACTION the frame is lost. (A converged, aligned frame that had lost
#: half its features was re-initialised: on an ISS tumble three frames of ~2 s each, and the
#: sequence's worst frame 0.18° off, 0.04° with relearning; bench/README.md, "Too few ...".)
MIN_KEPT_FRACTION = 0.5
MIN_TRACKED_FRACTION = 0.25
#: Attitude change (deg) since the Jacobian was learned after which it is learned again.
RELEARN_ROTATION_DEG = 6.0
#: Samples per pixel (at least) of the perturbation renders a tracked frame learns its Jacobian
#: from: noise in the rows shrinks the step along weakly seen directions, and the rest goes on
#: into the velocity. Started 0.2° off about the camera's x or y axis (Aura tumble, `rough`),
#: one step from rows at 4 spp left 0.055–0.18°, at 16 spp 0.005–0.075°; at 8 spp the sequences
#: drifted again. A relearning costs ~0.5 s more at 512² (13 renders at 256², 16 spp).
TRACK_PERTURBATION_SPP = 16
#: Floor of the robust residual scale (whitened px) of a tracker's LM, its full estimates too
#: (a single estimate's: 0.05): along a weakly seen direction few features show the error, and
#: at 0.05 Tukey dropped them (0.23 px out); an Aura approach then walked 0.4° a frame to 4.8°
#: off (bench/README.md, "A robust scale floor for tracking").
TRACK_ROBUST_FLOOR_PX = 0.3
#: Image motion (px, the largest of any feature) of the LM's first step below which a tracked
#: frame takes it without a trial render (worker.align.refine's linear_step_px): the step from
#: a good prediction moves the features by a few hundredths of a pixel, and its trial would
#: only measure them again (≤ 0.18 px on the ISS sequences at 512²; on a 192 × 144 sequence
#: steps of 0.3–0.5 px still gained 0.1–0.2° from a trial).
LINEAR_STEP_PX = 0.25
#: A motion (or a tracked frame's correction of its prediction) above this is a jump, no
#: velocity. Before any velocity, the motion into a re-initialised frame is one (without it, on
#: an Aura tumble of 2° a frame whose frame 1 was lost, frames 2-3 ended 0.56° and 0.54° off).
JUMP_DEG = 6.0
#: Motions averaged into the velocity: an error e_k a frame leaves along a weakly seen direction
#: (where the next frame's cost is flat and its start stands) enters the next start as
#: 2e_k − e_(k−1) from the last motion, as 4e_k/3 − e_(k−3)/3 from three (bench/README.md).
VELOCITY_FRAMES = 3
#: The LM's stop rules that count as converged.
CONVERGED = ("step_below_epsilon", "cost_converged", "linear_step")
#: Stop rules of an LM still moving (iterations out, or steps no longer shrinking): a frame that
#: aligns then learns afresh and goes on (Tracker._relearn) instead of a ~3-s full estimate (on
#: 16 sequences 18 of them → 5, errors alike; bench/README.md, "An unfinished frame goes on").
UNFINISHED = ("max_iterations", "slow")


class Tracker:
    """Estimates the pose in each frame of a sequence, in order (see the module docstring)."""

    def __init__(
        self, model: LoadedModel, request: EstimateRequest, should_cancel: CancelCheck | None = None
    ) -> None:
        # The frames share one renderer and carry feature positions from frame to frame in
        # the whole image's pixels: no refinement window (its origin would move with the target).
        options = request.options.model_copy(update={"window": False})
        self.model, self.should_cancel = model, should_cancel
        self.request = request.model_copy(update={"options": options})
        self.poses: list[Pose] = []
        #: The motions (increments [δq, δt]) into the last tracked frames: their mean is the
        #: velocity predicted() adds to the last pose.
        self._motions: list[Array] = []
        self._last_full = False  # whether the last frame was a full estimate
        self._misalignment: list[float] = []
        self._memory: Memory | None = None
        #: The request's sun (a full estimate's ``requested_lighting``): the prior of a tracked
        #: frame's sun fit, not the tilted sun the renderer was left with.
        self._requested: LightingSpec | None = None
        #: The model's outline vertices (model frame), whose image bounds each sky window.
        self._points = outline_points(model)

    # -- the sequence ---------------------------------------------------------------------
    def track(self, image: FloatImage, truth: Pose | None = None) -> FrameResult:
        """The next frame's pose (``truth``: its true pose, for the errors)."""
        start = time.perf_counter()
        index = len(self.poses)
        cam = self.request.camera
        check_size(image, cam.width, cam.height)
        if self._memory is None:
            R0, t0 = pose_from_schema(self.request.initial_pose)
            frame = self._full(image, (R0, t0), truth, index, start, "reinitialised")
        else:
            frame = self._tracked(image, truth, index, start)
        if self.poses and frame.status != "lost":
            self._observe(frame)
        self._last_full = frame.status == "reinitialised"
        self.poses.append((frame.R, frame.t))
        if frame.status != "lost":
            self._misalignment.append(1.0 - frame.alignment_score)
        return frame

    def _observe(self, frame: FrameResult) -> None:
        """The velocity's motions: a tracked frame's joins them unless it ended a jump from its
        prediction (caught by learning afresh: as a velocity it predicted the jump again and
        the next frames were lost); the first motion, or one between two full estimates,
        starts them again unless it is a jump; a re-initialisation's alone is none."""
        R1, t1 = self.poses[-1]
        motion = increment_between(R1, t1, frame.R, frame.t)
        if frame.status == "tracked":
            if rotation_error_deg(self.predicted()[0], frame.R) <= JUMP_DEG:
                self._motions = [*self._motions, motion][-VELOCITY_FRAMES:]
        elif not self._motions or self._last_full:
            if rotation_error_deg(R1, frame.R) <= JUMP_DEG:
                self._motions = [motion]

    def _misaligned(self, score: float) -> bool:
        """Whether a frame's alignment score is far below the last frames'."""
        recent = self._misalignment[-MISALIGNMENT_FRAMES:]
        level = float(np.median(recent)) if recent else 0.0
        return 1.0 - score > max(MISALIGNMENT_GROWTH * level, MIN_MISALIGNMENT)

    def _lost(self, reason: str, score: float, n_features: int, learned: int) -> bool:
        """The referee: whether a tracked frame is lost (its LM's stop rule, :meth:`_holds`)."""
        return reason not in CONVERGED or not self._holds(score, n_features, learned)

    def _holds(self, score: float, n_features: int, learned: int) -> bool:
        """Whether a frame's last render explains the image (its alignment score) and it still
        fits enough of the ``learned`` features."""
        return (
            score >= MIN_TRACK_SCORE
            and not self._misaligned(score)
            and n_features >= MIN_TRACKED_FRACTION * learned
        )

    def predicted(self) -> Pose:
        """The next pose by constant velocity: the last pose moved by the mean of the last
        VELOCITY_FRAMES motions :meth:`_observe` kept (the last pose itself before any)."""
        R1, t1 = self.poses[-1]
        if not self._motions:
            return R1, t1
        return apply_increment(R1, t1, np.mean(self._motions, axis=0))

    # -- a full estimate (first frame, re-initialisation) ---------------------------------
    def _full(
        self, image: FloatImage, guess: Pose, truth: Pose | None, index: int, start: float,
        status: str, search: bool = False,
    ) -> FrameResult:  # fmt: skip
        """A full estimate from ``guess``, then a relearning frame's pass (:meth:`_relearn`,
        rows at TRACK_PERTURBATION_SPP) from features made afresh where it ended; the next frames
        go on from them (bench/README.md, "A fresh feature set after each full estimate"; "A full
        estimate finished by a pass from fresh rows": over 0.15° 4 → 0 of 45, ~0.5 s)."""
        opts = self.request.options  # a search asked for in the request stands
        opts = opts.model_copy(update={"attitude_search": search or opts.attitude_search})
        update = {"initial_pose": pose_to_schema(*guess), "ground_truth": None, "options": opts}
        request = self.request.model_copy(update=update)
        est = estimate(
            self.model, image, request, should_cancel=self.should_cancel, window_sensors=True,
            robust_floor_px=TRACK_ROBUST_FLOOR_PX,
        )  # fmt: skip
        session = est.session
        assert session is not None
        self._requested = session.requested_lighting
        r = est.result
        renders, cost, pose = r.renders, r.render_cost, (session.R, session.t)
        score, n_features, covariance = r.alignment_score, r.features, r.covariance
        st, self._memory = session.last_stage, None
        if st is not None and isinstance(st.features, TrackedFeatures):
            fresh = self._session(session, image, pose, truth)
            try:
                state, _ = self._relearn(fresh, st, always=True)
            except ProxposeError:  # the estimate's pose and its own last set, then
                self._memory = Memory.learned_here(st, session)
            else:
                self._memory, pose = Memory.learned_here(state, fresh), (fresh.R, fresh.t)
                score, covariance = self._score(fresh), covariance_of(fresh)
                n_features = fresh.fit.features if fresh.fit is not None else n_features
            renders, cost = renders + fresh.renders, round(cost + fresh.render_cost, 3)
        return FrameResult(
            index, *pose, status, r.converged, time.perf_counter() - start, renders, cost,
            score, n_features, covariance, errors_between(truth, *pose), reason=r.reason,
        )  # fmt: skip

    # -- a tracked frame ------------------------------------------------------------------
    def _tracked(
        self, image: FloatImage, truth: Pose | None, index: int, start: float
    ) -> FrameResult:
        """A frame from the previous one's state; when its LM does not converge (after a
        pass from fresh rows when it was only still moving, UNFINISHED), or the referee rejects
        the frame, a full estimate (:meth:`_recover`)."""
        memory = self._memory
        assert memory is not None
        R_p, t_p = self.predicted()
        session = self._session(memory.session, image, (R_p, t_p), truth)
        try:
            reason = self._lm(session, self._carry(memory, session))
            if reason in CONVERGED and law_misplaced(memory.state.features, R_p, session.R):
                again = self._session(memory.session, image, (session.R, session.t), truth)
                reason = self._lm(again, self._carry(memory, again))
                again.renders += session.renders
                again.render_cost += session.render_cost
                session = again
            score = self._score(session)
        except TooFewFeaturesError:
            score, reason = -1.0, "too_few_features"
        fit = session.fit
        n_features = fit.features if fit is not None else 0
        learned, fresh = memory.learned_features, None
        if reason in UNFINISHED and self._holds(score, n_features, learned):
            # Still moving when its iterations ran out, and aligned: learn the rows afresh
            # where it got to and go on from there (the sun with it), not a full estimate.
            try:
                fresh, reason = self._relearn(session, memory.state, always=True)
            except TooFewFeaturesError:
                score, reason = -1.0, "too_few_features"
            else:
                assert session.fit is not None
                score, n_features = self._score(session), session.fit.features
                learned = int(fresh.ok.sum())
        if self._lost(reason, score, n_features, learned):
            guess = (session.R, session.t) if self._holds(score, 0, 0) else (R_p, t_p)
            return self._recover(image, guess, truth, index, start)
        if fresh is not None:
            self._memory, relearned = Memory.learned_here(fresh, session), True
        else:
            relearned = self._keep(session, memory, n_features)
        return FrameResult(
            index, session.R, session.t, "tracked", score >= MIN_CONVERGED_SCORE,
            time.perf_counter() - start, session.renders, round(session.render_cost, 3), score,
            n_features, covariance_of(session), errors_between(truth, session.R, session.t),
            relearned, reason,
        )  # fmt: skip

    @staticmethod
    def _score(session: Session) -> float:
        """The referee's alignment score, of the last render (after a linear step: its start)."""
        current = session.current
        assert current is not None
        return alignment_score(session.ref_grey, current.grey, work_box(current))

    @staticmethod
    def _lm(session: Session, state: StageState) -> str:
        """The frame's LM from the prediction, then its rows measured along the weakest
        directions and its step solved again (worker.align.weakprobe)."""
        reason = run_lm_stage(
            session, "klt", "refine", fit_sun=False, state=state, linear_step_px=LINEAR_STEP_PX
        )
        if reason in CONVERGED:
            probe_weak_directions(session)
        return reason

    def _session(
        self, previous: Session, image: FloatImage, guess: Pose, truth: Pose | None
    ) -> Session:
        spp = max(previous.options.perturbation_spp, TRACK_PERTURBATION_SPP)
        opts = previous.options.model_copy(
            update={"max_iterations": FRAME_ITERATIONS, "perturbation_spp": spp}
        )
        session = Session(
            renderer=previous.renderer,
            reference=image,
            reference_grey=to_grey(image),
            options=opts,
            R=guess[0],
            t=guess[1],
            truth=truth,
            should_cancel=self.should_cancel,
            rng=previous.rng,
            perturbation_scales=previous.perturbation_scales,
            robust_floor_px=TRACK_ROBUST_FLOOR_PX,
        )
        assert self._requested is not None
        session.requested_lighting = self._requested
        keep = previous.sky_window[0] if previous.sky_window else None
        session.sky_window = sky_window(self._points, session, guess, keep)
        return session

    def _carry(self, memory: Memory, session: Session) -> StageState:
        """The previous frame's features and Jacobian rows, moved into this frame."""
        st = memory.state
        assert st.learned is not None
        R1, t1 = self.poses[-1]
        dp = increment_between(R1, t1, session.R, session.t)
        J = np.nan_to_num(st.learned.J)
        motion = (J @ dp).reshape(-1, 2)
        view = session.current_view()
        features, keep = st.features.carried(session, view, motion)  # type: ignore[union-attr]
        h, ok = features.measure(view, (st.h + motion)[keep])
        rows = np.repeat(keep, 2)
        learned = LearnedJacobian(st.learned.J[rows], st.learned.ok[keep], st.learned.B, 0)
        return StageState(features, h, ok & st.ok[keep], learned, learned_at=view, level=view.level)

    def _keep(self, session: Session, memory: Memory, fitted: int) -> bool:
        """Remember this frame's state for the next; learn the Jacobian afresh (with new
        features) when the attitude has turned far since, too few features are left, or the
        rows mispredicted a trial (:func:`mispredicted`), and then solve for the sun's tilt
        again too, the pose with it (measured: bench/README.md, "The sun solved again at each
        relearning", "A rejected trial learns the rows again")."""
        st = session.last_stage
        turned = rotation_error_deg(memory.learned_pose[0], session.R)
        left = min(int(st.ok.sum()), fitted)  # fitted: the features the frame's fit used
        fresh_due = mispredicted(session) or turned >= RELEARN_ROTATION_DEG
        if not fresh_due and left >= MIN_KEPT_FRACTION * memory.learned_features:
            self._memory = Memory(st, memory.learned_pose, memory.learned_features, session)
            return False
        fresh, _ = self._relearn(session, st)
        self._memory = Memory.learned_here(fresh, session)
        return True

    def _relearn(
        self, session: Session, carried: StageState, always: bool = False
    ) -> tuple[StageState, str]:
        """Features and rows made afresh at the session's pose, and (with options.fit_sun, or
        ``always``) an LM pass from them, the sun's tilt solved too with fit_sun; returns them
        and the pass's stop rule. Without ``always`` a pass short of features leaves the pose."""
        fresh = self._fresh(session)
        fresh.features.smeared = inherited_smear(  # type: ignore[attr-defined]
            carried.features, fresh.features
        )
        reason = "cost_converged"
        if session.options.fit_sun or always:
            session.options = session.options.model_copy(
                update={"max_iterations": len(session.history) + FRAME_ITERATIONS}
            )
            try:
                reason = run_lm_stage(
                    session, "klt", "refine", fit_sun=session.options.fit_sun, state=fresh
                )
            except TooFewFeaturesError:
                if always:
                    raise
            fresh.sun_J = None  # the next frames keep this sun and solve for the pose only
        return fresh, reason

    _fresh = staticmethod(fresh_state)

    def _recover(
        self, image: FloatImage, guess: Pose, truth: Pose | None, index: int, start: float
    ) -> FrameResult:
        """The frame is lost: a full estimate from the prediction, failing that one that searches
        the attitude first (options.attitude_search; unless the first did) and aligns; or lost."""
        for search in (False,) if self.request.options.attitude_search else (False, True):
            try:
                frame = self._full(image, guess, truth, index, start, "reinitialised", search)
                if frame.converged and (not search or self._holds(frame.alignment_score, 0, 0)):
                    return frame
            except ProxposeError:
                pass
        R, t = guess
        return FrameResult(
            index, R, t, "lost", False, time.perf_counter() - start, 0, 0.0, -1.0, 0,
            None, errors_between(truth, R, t),
        )  # fmt: skip
