"""Perturbation renders and the learned Jacobian at the current pose (docs/method.md, steps 2–4)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from worker.align.edges import normal_shift
from worker.align.features import track
from worker.align.jacobian import (
    learn_jacobian,
    learn_jacobian_per_feature,
    sample_perturbations,
)
from worker.align.session import Session
from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.photometry import smooth, to_u8
from worker.engine.posemath import apply_increment, matrix_to_axis_angle

Array = NDArray[np.float64]

#: Times the perturbations are shrunk and re-drawn when too few features survive.
MAX_RESAMPLES = 3


@dataclass
class LearnedJacobian:
    J: Array  # (2k, 6), NaN rows for features without a fit
    ok: NDArray[np.bool_]  # (k,) features with a usable fit
    B: Array  # (6, N_s)
    renders: int


def apparent_radius_px(
    f_px: float, radius: float, distance: float, width_px: int, height_px: int
) -> float:
    """Apparent radius of the target, f·r/d px, but at most the image's half diagonal.

    A rotation θ about the target's centre moves a point at distance ρ from it by about f·θ·ρ/d
    px; only what is in view moves the features, so when the target overfills the frame (the
    camera inside its bounding sphere: terrain, docking range) ρ is bounded by the footprint of
    the field of view, not by the model's radius (which would shrink the perturbations until
    the features barely move).
    """
    return min(f_px * radius / max(distance, 1e-12), 0.5 * float(np.hypot(width_px, height_px)))


def perturbation_sizes(session: Session, shrink: float = 1.0) -> tuple[float, Array]:
    """Rotation cap (rad) and translation half-widths (3,) of the perturbations.

    By default sized so that each moves the image by about ``perturbation_px``: the target's
    apparent radius s = f·r/d px (:func:`apparent_radius_px`) turns a rotation θ into ≈ s·θ px,
    a lateral shift δ into f·δ/d and a shift in depth δz into s·δz/d.
    """
    opts = session.options
    model = session.renderer.model
    d = float(np.linalg.norm(session.R @ model.centre + session.t))
    cam = session.camera
    f = 0.5 * (cam.fx + cam.fy)
    s_px = max(apparent_radius_px(f, model.radius, d, cam.width, cam.height), 1.0)
    px = opts.perturbation_px * shrink
    if opts.perturbation_rot_deg is not None:
        angle = np.radians(opts.perturbation_rot_deg) * shrink
    else:
        angle = px / s_px
    if opts.perturbation_trans_frac is not None:
        half = np.full(3, opts.perturbation_trans_frac * session.range_ * shrink)
    else:
        half = np.array([px * d / f, px * d / f, px * d / s_px])
    return float(angle), half


def learn_at_pose(session: Session, points: Array, normals: Array | None = None) -> LearnedJacobian:
    """Render N_s perturbations around the session's pose and learn J for ``points`` (k, 2).

    ``points`` are feature positions in the render at the current pose and level. They are
    tracked from a base render into each perturbed render at the level's perturbation scale
    (KLT for 2-D features; for edge points, those with a unit normal in ``normals`` and not NaN,
    the shift across the edge, stored as s·n); E holds the displacements in the level's pixels.
    """
    opts = session.options
    # Perturbation-render pixels per level pixel, per axis, and where the level's principal
    # point falls there: the map between the two images (whole or windowed) is u' = a·u + b.
    level_cam, pert_cam = session.camera, session.perturbation_camera
    scale = np.array([pert_cam.fx / level_cam.fx, pert_cam.fy / level_cam.fy])
    shift = np.array([pert_cam.cx, pert_cam.cy]) - scale * [level_cam.cx, level_cam.cy]
    k = len(points)
    axis, angle = matrix_to_axis_angle(session.R)
    centre_axis = axis if angle > 1e-6 else None
    renders = 0
    for attempt in range(MAX_RESAMPLES + 1):
        shrink = 0.5**attempt
        max_angle, half = perturbation_sizes(session, shrink)
        B = sample_perturbations(
            session.rng,
            opts.n_samples,
            max_angle,
            half,
            centre_axis,
            np.radians(opts.axis_cone_deg),
        )
        base_seed = opts.seed + 1000 * (attempt + 1)
        base = session.render_perturbed(session.R, session.t, base_seed)
        renders += 1
        white = float(np.percentile(base, 99.9)) or 1.0
        base8 = smooth(to_u8(base, white))
        pts_s = points * scale + shift
        E = np.full((2 * k, opts.n_samples), np.nan)
        for i in range(opts.n_samples):
            R_i, t_i = apply_increment(session.R, session.t, B[:, i])
            img = session.render_perturbed(R_i, t_i, base_seed + i + 1)
            renders += 1
            with session.timed("track"):
                d, ok = _displacements(base, base8, img, white, pts_s, normals)
            d = d / scale
            E[0::2, i] = np.where(ok, d[:, 0], np.nan)
            E[1::2, i] = np.where(ok, d[:, 1], np.nan)
        learned = _fit(E, B, opts.jacobian, renders)
        if learned.ok.sum() >= opts.min_features:
            return learned
    raise TooFewFeaturesError(
        f"only {int(learned.ok.sum())} features could be tracked through the perturbed "
        f"renders (need {opts.min_features})"
    )


def _displacements(
    base: Array,
    base8: NDArray[np.uint8],
    img: Array,
    white: float,
    pts: Array,
    normals: Array | None,
) -> tuple[Array, NDArray[np.bool_]]:
    """Motion (k, 2) of each point from the base render to ``img``: KLT for 2-D features,
    the shift across the edge (as s·n) for edge points."""
    img8 = smooth(to_u8(img, white))
    edge = np.zeros(len(pts), dtype=bool) if normals is None else np.isfinite(normals[:, 0])
    d = np.zeros_like(pts)
    ok = np.zeros(len(pts), dtype=bool)
    if (~edge).any():
        moved, ok_c = track(base8, img8, pts[~edge], levels=2)
        d[~edge], ok[~edge] = moved - pts[~edge], ok_c
    if edge.any():
        assert normals is not None
        n = normals[edge]
        s, ok_e = normal_shift(base8.astype(np.float32), img8.astype(np.float32), pts[edge], n)
        d[edge], ok[edge] = s[:, None] * n, ok_e
    return d, ok


def _fit(E: Array, B: Array, mode: str, renders: int) -> LearnedJacobian:
    if mode == "common":  # the paper: drop features lost in any view
        seen = np.isfinite(E[0::2]).all(axis=1) & np.isfinite(E[1::2]).all(axis=1)
        J = np.full((E.shape[0], 6), np.nan)
        if seen.any():
            rows = np.repeat(seen, 2)
            J[rows] = learn_jacobian(E[rows], B)
        return LearnedJacobian(J, seen, B, renders)
    J, ok = learn_jacobian_per_feature(E, B)
    return LearnedJacobian(J, ok, B, renders)


def analytic_jacobian(
    session: Session, points: Array, normals: Array | None = None
) -> LearnedJacobian:
    """J from geometry instead of perturbed renders: cast rays through ``points`` (k, 2) in
    the render at the current pose, and differentiate the projection of the surface points hit
    with respect to the local increment [δq, δt] (central differences). Features whose ray
    misses the model (silhouette points against the sky) get no rows. Edge points keep only
    the component across the edge, like their learned rows. No render is made: this is the
    'fast' method's alternative to docs/method.md steps 2–4, not the paper's learned Jacobian.
    """
    X, hit = session.raycast(session.R, session.t, points)
    k = len(points)
    J = np.full((2 * k, 6), np.nan)
    cam = session.camera
    _, half = perturbation_sizes(session)
    steps = np.concatenate([np.full(3, 1e-4), 1e-3 * half])
    cols = []
    for i in range(6):
        dp = np.zeros(6)
        dp[i] = steps[i]
        Rp, tp = apply_increment(session.R, session.t, dp)
        Rm, tm = apply_increment(session.R, session.t, -dp)
        up = cam.project(X[hit] @ Rp.T + tp)
        um = cam.project(X[hit] @ Rm.T + tm)
        cols.append(((up - um) / (2 * steps[i])).ravel())
    Jh = np.column_stack(cols)  # (2·hits, 6)
    if normals is not None:
        n = normals[hit]
        edge = np.isfinite(n[:, 0])
        P = np.where(
            edge[:, None, None],
            np.einsum("ki,kj->kij", np.nan_to_num(n), np.nan_to_num(n)),
            np.eye(2),
        )
        Jh = np.einsum("kij,kjn->kin", P, Jh.reshape(-1, 2, 6)).reshape(-1, 6)
    J[np.repeat(hit, 2)] = Jh
    return LearnedJacobian(J, hit.copy(), np.zeros((6, 0)), 0)


#: Median predicted feature motion (px) below which a step does not update the Jacobian.
BROYDEN_MIN_MOTION_PX = 0.3


def broyden_update(
    session: Session,
    J: Array,
    h: Array,
    idx: NDArray[np.intp],
    h_new: Array,
    dp: Array,
    sun_motion: Array | None = None,
    min_motion_px: float = BROYDEN_MIN_MOTION_PX,
) -> None:
    """Correct the learned rows ``J`` (2k, 6) of features ``idx`` along the step ``dp`` just
    taken, in place (Broyden's rank-1 update).

    After an accepted step the features' actual motion h_new − h is known; J_k gains
    (Δh_k − J_k δp) s'ᵀ / s'ᵀs' in parameters scaled by the perturbation sizes (so rotation
    and translation count alike). Skipped for steps whose predicted motion is within the
    measurement noise, where the update would learn noise (``min_motion_px``: that floor; 0
    for a step measured on purpose, worker.align.weakprobe). ``sun_motion`` (2k,): the part of
    the motion a change of the sun explains.
    """
    rows = np.concatenate([2 * idx[:, None], 2 * idx[:, None] + 1], axis=1).ravel()
    predicted = J[rows] @ dp
    if np.median(np.abs(predicted)) < min_motion_px:
        return
    angle, half = perturbation_sizes(session)
    S = np.concatenate([np.full(3, 0.5 * angle), half])
    s = dp / S
    moved = (h_new[idx] - h[idx]).ravel()
    if sun_motion is not None:
        moved = moved - sun_motion[rows]
    J[rows] += np.outer(moved - predicted, s / (s @ s)) / S
