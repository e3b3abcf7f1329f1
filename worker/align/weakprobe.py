"""A tracked frame's rows measured along the directions its features see least.

Why. A tracked frame takes one step (or a few) from a constant-velocity prediction with rows
learned frames earlier. Where the target is small in the frame, two directions of the pose
move the features least: each out-of-plane rotation traded against a lateral shift (their
geometric σ ~100× the best-seen direction's, for the demo satellite at 640×480). Learned rows
get those near-cancellations wrong by more than they are (their tracking noise is a few per
cent of each column; worker/align/geometric.py), so the step from
the prediction corrects a fifth of the prediction's error there or less, and the error goes on
into the velocity: the next prediction carries it further, and the track walks (the demo
satellite's fly-around at 640×480: 0.07° after the first frame, 0.56° eight frames later;
with the true velocity in place of the estimated one, every frame within 0.17°).

What. After the frame's LM has converged, the PROBE_CANDIDATES weakest directions of the
geometric information (ray-cast rows of the frame's own features, as the geometric pass and the
'fast' method use, in rotation and range-scaled translation) are compared with the learned
rows, and the one they predict least like the geometry is probed: a render at the frame's pose
moved PROBE_DEG along it, the features measured there. The learned rows are corrected to
reproduce the measured motion from the frame's render (Broyden's rank-1 secant update, in the
perturbation-scaled parameters), and the step from the frame's render is solved again with
them. The rows stay learned from renders; the geometry only says where to look. The corrected
rows go on to the next frames (the other direction is probed when it is the worse one). One
render at PROBE_SPP and one measurement a frame (~0.05 s at 512²).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from worker.align.learning import analytic_jacobian, broyden_update
from worker.align.lm import lm_step, rows_of, weighted_cost, whiten
from worker.align.session import LinearFit, Session
from worker.align.tracked import Features
from worker.engine.posemath import apply_increment, increment_between, step_norm

Array = NDArray[np.float64]

#: Directions a frame chooses its probe from: the geometry's weakest (a small target's two
#: out-of-plane rotations, each traded against a lateral shift).
PROBE_CANDIDATES = 2
#: A frame probes only when, along the chosen direction, the learned rows' predicted motion
#: differs from the geometry's by at least this share of it (whitened, over the features).
#: Tracks that walked (the demo satellite's fly-around at 640×480) showed 0.7-3.2 on their
#: frames, the rows overstating the motion 1.4-3.2×; tracks that held (ISS and Aura
#: approaches at 512²) 0.3-0.6, but their first frames.
PROBE_MIN_DISAGREEMENT = 0.8
#: How far each probe moves the pose along its direction, degrees (or the range's share).
PROBE_DEG = 1.0
#: Samples per pixel of the probe's render: a 512² render at 4 spp takes 18 ms, at the main
#: 16 spp 46 ms.
PROBE_SPP = 4
#: A corrected step that moves the pose further than this from the LM's (degrees, with the
#: translation as a share of the range) is not taken: the probe measured something else.
MAX_CORRECTION_DEG = 1.0


def probe_weak_directions(session: Session) -> bool:
    """Measure the learned rows along the frame's weakest direction, correct them and solve
    the step from the frame's render again (see the module docstring). Returns whether the
    pose moved. Nothing happens without a converged stage of 6 pose columns, a current render,
    enough features with geometric rows (silhouette points against the sky have none) or
    found in the probe's render, or when the corrected step moves the pose further than
    MAX_CORRECTION_DEG from the LM's."""
    st, fit, base = session.last_stage, session.fit, session.current
    if st is None or st.learned is None or fit is None or base is None or fit.J.shape[1] != 6:
        return False
    active = st.active
    if len(fit.w) != active.sum():
        return False
    features, J = st.features, st.learned.J
    # Where the features are in the render the step starts from: measured there, and moved
    # by the rows since when the LM's last step was a linear one (no render at its end).
    h0 = st.h.copy()
    moved = increment_between(base.R, base.t, session.R, session.t)
    h0[active] -= (J[rows_of(active)] @ moved).reshape(-1, 2)
    scale = np.concatenate([np.full(3, 2.0), np.full(3, 1.0 / session.range_)])
    u = _weakest(session, features, J, h0, active, scale)
    if u is None:
        return False  # too few ray-cast rows, or the learned rows agree with them
    R, t = apply_increment(session.R, session.t, u * np.radians(PROBE_DEG) / scale)
    step = increment_between(base.R, base.t, R, t)
    kept, session.stage_spp = session.stage_spp, PROBE_SPP
    try:
        view = session.render_view(R, t)
    finally:
        session.stage_spp = kept
    with session.timed("track"):
        h, found = features.measure(view, h0 + (np.nan_to_num(J) @ step).reshape(-1, 2))
    found &= st.ok & st.learned.ok
    if (found & active).sum() < session.options.min_features:
        return False
    # Broyden's update along the probe's step, without its floor on the motion: here the
    # motion is small by design, and measured from a render, not a trial's prediction.
    corrected = J.copy()
    broyden_update(session, corrected, h0, np.flatnonzero(found), h, step, min_motion_px=0.0)
    used = found[active]
    A = features.A[active]
    J_w = whiten(A, corrected[rows_of(active)])
    r0 = np.where(np.repeat(used, 2), whiten(A, (features.x_ref - h0)[active].ravel()), 0.0)
    w = fit.w * used
    dp = lm_step(J_w, r0, session.options.lambda_init, w)
    R, t = apply_increment(base.R, base.t, dp)
    if step_norm(increment_between(session.R, session.t, R, t), session.range_) > np.radians(
        MAX_CORRECTION_DEG
    ):
        return False
    J[:] = corrected
    session.R, session.t = R, t
    st.h = h0 + (np.nan_to_num(J) @ dp).reshape(-1, 2)
    r = r0 - J_w @ dp
    session.fit = LinearFit(J_w, r, w, st.h[active])
    n = int(used.sum())
    session.record("refine", weighted_cost(r, w), step_norm(dp, session.range_), 0.0, True, n)
    return True


def _weakest(
    session: Session,
    features: Features,
    J: Array,
    h: Array,
    active: NDArray[np.bool_],
    scale: Array,
) -> Array | None:
    """Of the PROBE_CANDIDATES directions (unit, in rotation and range-scaled translation) of
    least geometric information over the active features with ray-cast rows, the one along
    which the learned rows ``J`` predict the features' motion least like the geometry; None
    when fewer than six features have ray-cast rows, or when along it the learned rows' error
    is under PROBE_MIN_DISAGREEMENT of the geometric motion."""
    geo = analytic_jacobian(session, h, features.feature_normals).J
    hit = active & np.isfinite(geo).reshape(-1, 2, 6).all(axis=(1, 2))
    if hit.sum() < 6:
        return None
    A = features.A[hit]
    G = whiten(A, geo[rows_of(hit)]) / scale
    _, V = np.linalg.eigh(G.T @ G)
    L = whiten(A, np.nan_to_num(J[rows_of(hit)])) / scale
    candidates = V[:, :PROBE_CANDIDATES]
    disagreement = np.linalg.norm((L - G) @ candidates, axis=0)
    disagreement /= np.maximum(np.linalg.norm(G @ candidates, axis=0), 1e-12)
    worst = int(np.argmax(disagreement))
    return candidates[:, worst] if disagreement[worst] >= PROBE_MIN_DISAGREEMENT else None
