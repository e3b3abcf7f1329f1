"""The learned-Jacobian Levenberg–Marquardt stage (docs/method.md, steps 1–6).

Features are either fixed reference corners tracked into each render with KLT ('klt', the
default: one feature set for the whole stage, so the Jacobian can be reused while the pose moves
little) or descriptor matches re-made at each new pose ('matches', the paper). A trial pose is
judged on the same features as the current one: its render is measured for the features the
current cost used, and only then compared. With ``options.fit_sun`` the refinement also solves
for a tilt of the sun (:mod:`worker.align.sunfit`): two more columns of the Jacobian, moved by the
same steps and undone with a rejected one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from schemas.estimate import Stage
from worker.align.learning import (
    LearnedJacobian,
    analytic_jacobian,
    broyden_update,
    learn_at_pose,
)
from worker.align.lm import (
    TUKEY_C,
    Damping,
    capped_cost,
    feature_norms,
    irls_increment,
    ransac_increment,
    robust_scale,
    rows_of,
    weighted_cost,
    whiten,
)
from worker.align.session import LinearFit, RenderedView, Session
from worker.align.sunfit import SunTilt, step_with_sun
from worker.align.tracked import Features, MatchedFeatures, TrackedFeatures
from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.posemath import apply_increment, step_norm

Array = NDArray[np.float64]
Outcome = Literal[
    "step_below_epsilon",
    "cost_converged",
    "max_iterations",
    "stalled",
    "handover",
    "slow",
    "linear_step",
]

#: Consecutive rejected trials that end the stage (each costs a render; waiting for a third
#: changed no estimate by more than 0.0001° on 11 cases).
MAX_REJECTIONS = 2
#: λ beyond which repeated rejections end the stage.
LAMBDA_MAX = 1e4
#: Accepted steps in a row, each more than SLOW_RATIO (worker.align.lm) of the one before, that
#: end the stage as 'slow': with a right Jacobian the steps shrink fast; steady ones mean it
#: overstates how far the features move, and a Jacobian learned afresh at the current pose does
#: better.
SLOW_STEPS = 3
#: RANSAC threshold over δp: at least this, px, or a fraction of the median residual.
RANSAC_MIN_PX = 1.5
RANSAC_REL = 0.25


@dataclass
class StageState:
    """What a stage works on: its features, where they are in the current render, the learned
    Jacobian and the pose-consistent inliers. A tracker hands one from frame to frame."""

    features: Features
    h: Array  # (k, 2) positions in the current render
    ok: NDArray[np.bool_]  # (k,) found in the current render
    learned: LearnedJacobian | None = None
    learned_at: RenderedView | None = None  # the view whose pose the Jacobian was learned at
    inliers: NDArray[np.bool_] | None = None  # pose-consistent features (RANSAC)
    sun_J: Array | None = None  # (2k, 2) px per radian of sun tilt (see worker.align.sunfit)
    level: float = 1.0  # the session level the features were made at (their pixel scale)

    @property
    def active(self) -> NDArray[np.bool_]:
        """The features a step uses: found, with learned rows, and inliers once RANSAC ran."""
        assert self.learned is not None
        active = self.ok & self.learned.ok
        return active if self.inliers is None else active & self.inliers


def _new_state(session: Session, mode: str, view: RenderedView) -> StageState:
    with session.timed("match"):
        feats: Features = (
            TrackedFeatures(session, view) if mode == "klt" else MatchedFeatures(session, view)
        )
        h, ok = feats.measure(view, None)
    if ok.sum() < session.options.min_features:
        raise TooFewFeaturesError(
            f"only {int(ok.sum())} features found in common between the reference and the "
            f"render (need {session.options.min_features})"
        )
    return StageState(feats, h, ok, level=view.level)


def _weights(
    session: Session, st: StageState, J: Array, r: Array, active: NDArray[np.bool_]
) -> Array:
    """Per-feature weights over ``active``: RANSAC inliers on first use, then IRLS (Tukey)."""
    if not session.options.robust:
        return np.ones(int(active.sum()))
    if st.inliers is None:
        thr = max(RANSAC_MIN_PX, RANSAC_REL * float(np.median(feature_norms(r))))
        inl = ransac_increment(J, r, session.rng, thr)
        st.inliers = np.zeros(len(active), dtype=bool)
        st.inliers[np.flatnonzero(active)[inl]] = True
    w0 = st.inliers[active].astype(np.float64)
    if w0.sum() < 3:
        w0 = np.ones(len(w0))
    return irls_increment(J, r, w0=w0, floor=session.robust_floor_px)[1]


@dataclass
class _System:
    """The linearised problem at the current pose, over the active features (a of them)."""

    active: NDArray[np.bool_]  # (k,) the features in the system
    A: Array  # (a, 2, 2) their whitening
    J_px: Array  # (2a, 6) their learned rows, px
    J: Array  # (2a, n) whitened rows; n = 8 with the sun's tilt columns
    r: Array  # (2a,) whitened residuals
    w: Array  # (a,) weights
    cost: float  # weighted cost of r
    dp_all: Array  # (n,) the LM step over J's columns

    @property
    def dp(self) -> Array:
        """The pose part of the step, [δq, δt]."""
        return self.dp_all[:6]

    @property
    def ds(self) -> Array:
        """The sun's part of the step (empty without the sun's tilt)."""
        return self.dp_all[6:]


@dataclass
class _Trial:
    """A render at the pose the step leads to, and the active features measured in it."""

    view: RenderedView
    h: Array  # (k, 2) positions in the trial render
    ok: NDArray[np.bool_]  # (k,) found there
    common: NDArray[np.bool_]  # (a,) active features found in both renders
    r: Array  # (2a,) whitened residuals at the trial
    cost_now: float  # cost at the current pose over the common features
    cost: float  # cost at the trial over the same features
    capped_now: float  # the same two with each feature's share capped (see _judge)
    capped: float
    lost: bool  # too few common features to compare the two
    sun_motion: Array | None  # (2k,) image motion the trial's change of sun predicts


def run_lm_stage(
    session: Session,
    mode: str,
    stage: Stage,
    handover_step: float | None = None,
    fit_sun: bool | None = None,
    state: StageState | None = None,
    linear_step_px: float | None = None,
) -> Outcome:
    """Learned-Jacobian LM from the session's pose until a stop rule fires.

    Each iteration sets up the features and the Jacobian where needed (:func:`_ready_state`),
    solves the linear system for a step (:func:`_linear_system`), stops without a render when
    that step is negligible, else renders and measures a trial (:func:`_trial`) and accepts or
    rejects it (:func:`_judge`). With ``handover_step``, the stage ends ('handover') at the
    first accepted step smaller than it: used when the matches-based LM stands in for a failed
    PnP coarse stage. ``fit_sun`` (default: options.fit_sun, in the 'refine' stage) solves for
    the sun's tilt too; without it the sun stays as the renderer has it. ``state`` starts the
    stage from features and a Jacobian made before (a tracker's previous frame); the stage's
    state is kept in ``session.last_stage``. With ``linear_step_px``, a first step that moves
    no feature by as much as that (px) is taken without a trial render and ends the stage
    ('linear_step', see :func:`_take_linear_step`; a tracker's stage starts at a prediction);
    the session's current render then stays at the pose the step started from.
    """
    opts = session.options
    damping = Damping(opts.lambda_init)
    st: StageState | None = state
    fit_sun = opts.fit_sun and stage == "refine" if fit_sun is None else fit_sun
    sun = SunTilt(session) if fit_sun else None
    while session.iterations_left > 0:
        st = _ready_state(session, st, mode, session.current_view(), sun)
        session.last_stage = st
        system = _linear_system(session, st, damping.lam, sun)
        session.fit = LinearFit(system.J, system.r, system.w, st.h[system.active])
        step = step_norm(system.dp, session.range_)
        predicted_gain = system.cost - weighted_cost(system.r - system.J @ system.dp_all, system.w)
        if step < opts.epsilon or predicted_gain < opts.cost_tolerance * system.cost:
            # The linear model asks for a move below ε, or promises less than the tolerance:
            # converged, and no render is spent on a trial.
            session.record(stage, system.cost, step, damping.lam, False, int(system.active.sum()))
            return "step_below_epsilon" if step < opts.epsilon else "cost_converged"
        if linear_step_px is not None and sun is None and _motion_px(system) < linear_step_px:
            _take_linear_step(session, stage, st, system, step, damping.lam)
            return "linear_step"
        linear_step_px = None  # only a stage's first step: after a trial the LM goes on
        trial = _trial(session, st, system, sun)
        outcome = _judge(session, stage, st, system, trial, step, damping, handover_step)
        if outcome is not None:
            return outcome
    return "max_iterations"


def _ready_state(
    session: Session, st: StageState | None, mode: str, view: RenderedView, sun: SunTilt | None
) -> StageState:
    """The stage's state at ``view``: features made on first use (for 'matches', at each new
    view), the Jacobian learned on first use (without reuse, at each new pose), and the
    sun's columns once."""
    opts = session.options
    if st is None or (mode == "matches" and getattr(st.features, "view", None) is not view):
        st = _new_state(session, mode, view)
    if st.learned is None or (not opts.reuse_jacobian and st.learned_at is not view):
        with session.timed("jacobian"):
            if opts.jacobian == "analytic":
                st.learned = analytic_jacobian(session, st.h, st.features.feature_normals)
            else:
                st.learned = learn_at_pose(session, st.h, st.features.feature_normals)
        st.learned_at = view
    if sun is not None and st.sun_J is None:
        with session.timed("jacobian"):
            st.sun_J, seen = sun.jacobian(st.features.measure, view, st.h, st.ok)
        # A feature a 2° tilt of the sun loses is made by shading (a shadow edge, a terminator):
        # with zero sun columns the fit would read its shading-made offset as pose (over terrain
        # at a low sun a quarter of them; bench/README.md, "Features the sun's tilt loses").
        if (st.ok & seen).sum() >= opts.min_features:
            st.ok = st.ok & seen
    return st


def _linear_system(session: Session, st: StageState, lam: float, sun: SunTilt | None) -> _System:
    """Whitened rows and residuals of the usable features, their weights, and the LM step.

    Raises TooFewFeaturesError when fewer than ``min_features`` are usable.
    """
    opts = session.options
    assert st.learned is not None
    active = st.active
    if active.sum() < opts.min_features:
        raise TooFewFeaturesError(
            f"only {int(active.sum())} features usable (need {opts.min_features})"
        )
    A = st.features.A[active]
    J_px = st.learned.J[rows_of(active)]
    J = whiten(A, J_px)
    r = whiten(A, (st.features.x_ref - st.h)[active].ravel())
    with session.timed("solve"):
        w = _weights(session, st, J, r, active)
        if st.inliers is not None:
            active_new = st.active
            if not np.array_equal(active_new, active):  # RANSAC just ran: restrict
                keep = active_new[active]
                active, J, r, w = active_new, J[rows_of(keep)], r[rows_of(keep)], w[keep]
                A, J_px = A[keep], J_px[rows_of(keep)]
        if st.sun_J is not None:
            J = np.hstack([J, whiten(A, st.sun_J[rows_of(active)])])
        dp_all = step_with_sun(J, r, lam, w, sun)
    return _System(active, A, J_px, J, r, w, weighted_cost(r, w), dp_all)


def _motion_px(system: _System) -> float:
    """The largest image motion (px) the linear model predicts for the system's step (not
    the median: an approach moves the features near the centre of expansion little)."""
    return float(np.max(np.hypot(*(system.J_px @ system.dp).reshape(-1, 2).T), initial=0.0))


def _take_linear_step(
    session: Session, stage: Stage, st: StageState, system: _System, step: float, lam: float
) -> None:
    """Move by the system's step without rendering there: the features move as the learned
    rows predict, and the fit keeps the residuals the linear model leaves. For a step of a
    fraction of a pixel the linear model is as good as a measurement (a trial would re-measure
    the same features at a sub-pixel offset, and teach the Jacobian nothing: see
    BROYDEN_MIN_MOTION_PX)."""
    session.R, session.t = apply_increment(session.R, session.t, system.dp)
    moved = (system.J_px @ system.dp).reshape(-1, 2)
    st.h = st.h.copy()
    st.h[system.active] += moved
    r = system.r - system.J @ system.dp_all
    session.fit = LinearFit(system.J, r, system.w, st.h[system.active])
    session.record(stage, weighted_cost(r, system.w), step, lam, True, int(system.active.sum()))


def _trial(session: Session, st: StageState, system: _System, sun: SunTilt | None) -> _Trial:
    """Render at the pose the step leads to (the sun moved by its part of the step) and measure
    the features there, starting from where the linear model predicts them. The trial is judged
    on the same features as the current cost; one that cannot be judged, or does not lower
    the cost, puts the sun back."""
    R_t, t_t = apply_increment(session.R, session.t, system.dp)
    sun_before = sun.ab if sun is not None else None
    sun_motion = None
    if sun is not None and st.sun_J is not None:
        sun.set(sun.clip(sun.ab + system.ds))
        sun_motion = st.sun_J @ (sun.ab - sun_before)
    view = session.render_view(R_t, t_t)
    guess = st.h.copy()
    guess[system.active] += (system.J_px @ system.dp).reshape(-1, 2)
    if sun_motion is not None:
        guess += sun_motion.reshape(-1, 2)
    with session.timed("track"):
        h_t, ok_t = st.features.measure(view, guess)
    common = ok_t[system.active]
    r_t = whiten(system.A, (st.features.x_ref - h_t)[system.active].ravel())
    rows = rows_of(common)
    cap = TUKEY_C * robust_scale(feature_norms(system.r)[system.w > 0], session.robust_floor_px)
    trial = _Trial(
        view,
        h_t,
        ok_t,
        common,
        r_t,
        cost_now=weighted_cost(system.r[rows], system.w[common]),
        cost=weighted_cost(r_t[rows], system.w[common]),
        capped_now=capped_cost(system.r[rows], system.w[common], cap),
        capped=capped_cost(r_t[rows], system.w[common], cap),
        lost=bool(common.sum() < session.options.min_features),
        sun_motion=sun_motion,
    )
    if sun is not None and (trial.lost or trial.capped >= trial.capped_now):
        sun.set(sun_before)  # the trial is rejected: back to the sun it replaced
    return trial


def _judge(
    session: Session,
    stage: Stage,
    st: StageState,
    system: _System,
    trial: _Trial,
    step: float,
    damping: Damping,
    handover_step: float | None,
) -> Outcome | None:
    """Accept or reject the trial, record the iteration, update λ; the stage's outcome if a
    stop rule fires, else None."""
    opts = session.options
    n_common = int(trial.common.sum())
    if trial.lost:
        # The trial's render lost too many of the features to compare it on the same set:
        # treat it as a failed step (smaller next time).
        session.record(stage, system.cost, 0.0, damping.lam, False, n_common)
        damping.reject()
        return "stalled" if damping.rejected >= MAX_REJECTIONS else None
    # Capped costs: a few features that jump in the trial (at grazing light, as the sun tilts)
    # must not reject a step the rest confirm (see lm.capped_cost).
    if not trial.capped < trial.capped_now:  # (a NaN cost is a rejection too)
        session.record(stage, trial.cost_now, 0.0, damping.lam, False, n_common)
        damping.reject()
        if damping.rejected >= MAX_REJECTIONS:
            # No step, even a damped one, lowers the measured cost: the estimate sits in the
            # noise floor of the measurement.
            return "cost_converged"
        return "stalled" if damping.lam > LAMBDA_MAX else None
    session.accept(trial.view)
    assert st.learned is not None
    idx = np.flatnonzero(system.active)[trial.common]
    broyden_update(session, st.learned.J, st.h, idx, trial.h, system.dp, trial.sun_motion)
    st.h, st.ok = trial.h, st.ok & trial.ok
    rows = rows_of(trial.common)
    x = trial.h[system.active][trial.common]
    session.fit = LinearFit(system.J[rows], trial.r[rows], system.w[trial.common], x)
    session.record(stage, trial.cost, step, damping.lam, True, n_common)
    damping.accept(step)
    if damping.steady >= SLOW_STEPS - 1 and opts.reuse_jacobian and stage == "refine":
        return "slow"
    if handover_step is not None and step < handover_step:
        return "handover"
    if step < opts.epsilon:
        return "step_below_epsilon"
    if trial.capped_now - trial.capped < opts.cost_tolerance * trial.capped_now:
        return "cost_converged"
    return None
