"""The learned-Jacobian Levenberg–Marquardt stage (METHOD.md steps 1–6).

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
    learn_at_pose,
    perturbation_sizes,
)
from worker.align.lm import (
    feature_norms,
    irls_increment,
    lm_step,
    ransac_increment,
    weighted_cost,
)
from worker.align.session import LinearFit, RenderedView, Session
from worker.align.sunfit import SunTilt
from worker.align.tracked import Features, MatchedFeatures, TrackedFeatures
from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.posemath import apply_increment, step_norm

Array = NDArray[np.float64]
Outcome = Literal[
    "step_below_epsilon", "cost_converged", "max_iterations", "stalled", "handover", "slow"
]

#: Median predicted feature motion (px) below which a step does not update the Jacobian.
BROYDEN_MIN_MOTION_PX = 0.3
#: Consecutive rejected trials that end the stage.
MAX_REJECTIONS = 3
#: λ beyond which repeated rejections end the stage.
LAMBDA_MAX = 1e4
LAMBDA_MIN = 1e-9
#: Accepted steps in a row, each more than SLOW_RATIO of the one before, that end the stage as
#: 'slow': with a right Jacobian the steps shrink fast; steady ones mean it overstates how far
#: the features move, and a Jacobian learned afresh at the current pose does better.
SLOW_STEPS = 3
SLOW_RATIO = 0.5
#: RANSAC threshold over δp: at least this, px, or a fraction of the median residual.
RANSAC_MIN_PX = 1.5
RANSAC_REL = 0.25


@dataclass
class _State:
    features: Features
    h: Array  # (k, 2) positions in the current render
    ok: NDArray[np.bool_]  # (k,) found in the current render
    learned: LearnedJacobian | None = None
    learned_at: RenderedView | None = None  # the view whose pose the Jacobian was learned at
    inliers: NDArray[np.bool_] | None = None  # pose-consistent features (RANSAC)
    sun_J: Array | None = None  # (2k, 2) px per radian of sun tilt (see worker.align.sunfit)


def _rows(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    return np.repeat(mask, 2)


def _whiten(A: Array, X: Array) -> Array:
    """Rows (u, v) of each feature, in X (2k,) or (2k, n), multiplied by its A (k, 2, 2)."""
    k = len(A)
    Xk = X.reshape(k, 2, -1)
    return np.einsum("kij,kjn->kin", A, Xk).reshape(X.shape)


def _new_state(session: Session, mode: str, view: RenderedView) -> _State:
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
    return _State(feats, h, ok)


def _weights(session: Session, st: _State, J: Array, r: Array, active: NDArray[np.bool_]) -> Array:
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
    return irls_increment(J, r, w0=w0)[1]


def _step(J: Array, r: Array, lam: float, w: Array, sun: SunTilt | None) -> Array:
    """The LM step over J's columns; with the sun's tilt among them, its prior joins the solve."""
    if sun is None:
        return lm_step(J, r, lam, w)
    Jp, rp = sun.prior_rows()
    return lm_step(np.vstack([J, Jp]), np.concatenate([r, rp]), lam, np.append(w, 1.0))


def _broyden_update(
    session: Session,
    st: _State,
    active: NDArray[np.bool_],
    common: NDArray[np.bool_],
    h_new: Array,
    dp: Array,
    sun_motion: Array | None = None,
) -> None:
    """Correct each feature's learned rows along the step just taken (Broyden's rank-1 update).

    After an accepted step the features' actual motion h_new − h is known; J_k gains
    (Δh_k − J_k δp) s'ᵀ / s'ᵀs' in parameters scaled by the perturbation sizes (so rotation
    and translation count alike). Skipped for steps whose predicted motion is within the
    measurement noise, where the update would learn noise.
    """
    assert st.learned is not None
    idx = np.flatnonzero(active)[common]
    J = st.learned.J
    rows = np.concatenate([2 * idx[:, None], 2 * idx[:, None] + 1], axis=1).ravel()
    predicted = J[rows] @ dp
    if np.median(np.abs(predicted)) < BROYDEN_MIN_MOTION_PX:
        return
    angle, half = perturbation_sizes(session)
    S = np.concatenate([np.full(3, 0.5 * angle), half])
    s = dp / S
    moved = (h_new[idx] - st.h[idx]).ravel()
    if sun_motion is not None:  # the part of the motion the sun's tilt explains
        moved = moved - sun_motion[rows]
    J[rows] += np.outer(moved - predicted, s / (s @ s)) / S


def run_lm_stage(
    session: Session, mode: str, stage: Stage, handover_step: float | None = None
) -> Outcome:
    """Learned-Jacobian LM from the session's pose until a stop rule fires.

    With ``handover_step``, the stage ends ('handover') at the first accepted step smaller than
    it: used when the matches-based LM stands in for a failed PnP coarse stage.
    """
    opts = session.options
    lam = opts.lambda_init
    rejected = 0  # consecutive rejected trials
    steady, last_step = 0, np.inf  # accepted steps in a row that did not shrink by half
    st: _State | None = None
    sun = SunTilt(session) if opts.fit_sun and stage == "refine" else None
    while session.iterations_left > 0:
        view = session.current_view()
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
                st.sun_J = sun.jacobian(st.features.measure, view, st.h, st.ok)
        active = st.ok & st.learned.ok
        if st.inliers is not None:
            active &= st.inliers
        if active.sum() < opts.min_features:
            raise TooFewFeaturesError(
                f"only {int(active.sum())} features usable (need {opts.min_features})"
            )
        A = st.features.A[active]
        J_px = st.learned.J[_rows(active)]
        J = _whiten(A, J_px)
        r = _whiten(A, (st.features.x_ref - st.h)[active].ravel())
        with session.timed("solve"):
            w = _weights(session, st, J, r, active)
            if st.inliers is not None:
                active_new = st.ok & st.learned.ok & st.inliers
                if not np.array_equal(active_new, active):  # RANSAC just ran: restrict
                    keep = active_new[active]
                    active, J, r, w = active_new, J[_rows(keep)], r[_rows(keep)], w[keep]
                    A, J_px = A[keep], J_px[_rows(keep)]
            if st.sun_J is not None:
                J = np.hstack([J, _whiten(A, st.sun_J[_rows(active)])])
            dp_all = _step(J, r, lam, w, sun)
        dp, ds = dp_all[:6], dp_all[6:]
        session.fit = LinearFit(J, r, w, st.h[active])
        step = step_norm(dp, session.range_)
        cost_model = weighted_cost(r, w)
        predicted_gain = cost_model - weighted_cost(r - J @ dp_all, w)
        if step < opts.epsilon or predicted_gain < opts.cost_tolerance * cost_model:
            # The linear model asks for a move below ε, or promises less than the tolerance:
            # converged, and no render is spent on a trial.
            session.record(stage, cost_model, step, lam, False, int(active.sum()))
            return "step_below_epsilon" if step < opts.epsilon else "cost_converged"
        R_t, t_t = apply_increment(session.R, session.t, dp)
        sun_before = sun.ab if sun is not None else None
        sun_motion = None  # image motion (2k,) the trial's change of sun predicts
        if sun is not None and st.sun_J is not None:
            sun.set(sun.clip(sun.ab + ds))
            sun_motion = st.sun_J @ (sun.ab - sun_before)
        trial = session.render_view(R_t, t_t)
        guess = st.h.copy()
        guess[active] += (J_px @ dp).reshape(-1, 2)
        if sun_motion is not None:
            guess += sun_motion.reshape(-1, 2)
        with session.timed("track"):
            h_t, ok_t = st.features.measure(trial, guess)
        common = ok_t[active]
        r_t = _whiten(A, (st.features.x_ref - h_t)[active].ravel())
        cost_now = weighted_cost(r[_rows(common)], w[common])
        cost_trial = weighted_cost(r_t[_rows(common)], w[common])
        lost = common.sum() < opts.min_features
        if sun is not None and (lost or cost_trial >= cost_now):
            sun.set(sun_before)  # the trial is rejected: back to the sun it replaced
        if lost:
            # The trial's render lost too many of the features to compare it on the same set:
            # treat it as a failed step (smaller next time).
            session.record(stage, weighted_cost(r, w), 0.0, lam, False, int(common.sum()))
            lam *= 10.0
            rejected += 1
            if rejected >= MAX_REJECTIONS:
                return "stalled"
            continue
        if cost_trial < cost_now:
            rejected = 0
            session.accept(trial)
            _broyden_update(session, st, active, common, h_t, dp, sun_motion)
            st.h, st.ok = h_t, st.ok & ok_t
            session.fit = LinearFit(
                J[_rows(common)], r_t[_rows(common)], w[common], h_t[active][common]
            )
            session.record(stage, cost_trial, step, lam, True, int(common.sum()))
            lam = max(lam * 0.1, LAMBDA_MIN)
            steady, last_step = (steady + 1 if step > SLOW_RATIO * last_step else 0), step
            if steady >= SLOW_STEPS - 1 and opts.reuse_jacobian and stage == "refine":
                return "slow"
            if handover_step is not None and step < handover_step:
                return "handover"
            if step < opts.epsilon:
                return "step_below_epsilon"
            if cost_now - cost_trial < opts.cost_tolerance * cost_now:
                return "cost_converged"
        else:
            session.record(stage, cost_now, 0.0, lam, False, int(common.sum()))
            lam *= 10.0
            rejected += 1
            if rejected >= MAX_REJECTIONS:
                # No step, even a damped one, lowers the measured cost: the estimate sits in
                # the noise floor of the measurement.
                return "cost_converged"
            if lam > LAMBDA_MAX:
                return "stalled"
    return "max_iterations"
