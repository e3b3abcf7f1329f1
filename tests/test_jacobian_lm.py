"""The learned Jacobian (worker/align/jacobian.py) and the LM machinery (worker/align/lm.py), on
synthetic linear maps and on a pinhole projection of 3D points (docs/method.md, "Signs")."""

from __future__ import annotations

import numpy as np
import pytest

from worker.align.jacobian import (
    MAX_DESIGN_CONDITION,
    design_condition,
    learn_jacobian,
    learn_jacobian_per_feature,
    sample_cap_angles,
    sample_perturbations,
)
from worker.align.lm import covariance, irls_increment, lm_step, ransac_increment, weighted_cost
from worker.engine.camera import PinholeCamera
from worker.engine.metrics import rotation_error_deg
from worker.engine.posemath import apply_increment, axis_angle_to_matrix, gibbs_to_matrix

HALF_WIDTH = np.array([0.05, 0.05, 0.2])  # translation box, scene units


def _design(rng: np.random.Generator, n: int) -> np.ndarray:
    """A perturbation design B (6, n) as the estimator draws it: rows of very different size."""
    return sample_perturbations(rng, n, np.radians(1.0), HALF_WIDTH)


# -- learning J ---------------------------------------------------------------------------
def test_learn_jacobian_recovers_a_linear_map_exactly() -> None:
    rng = np.random.default_rng(0)
    for n in (6, 12, 40):
        B = _design(rng, n)
        J_true = rng.normal(size=(50, 6)) * [300, 300, 300, 20, 20, 5]  # px per unit of each
        J = learn_jacobian(J_true @ B, B)
        np.testing.assert_allclose(J, J_true, rtol=1e-8, atol=1e-8 * np.abs(J_true).max())


def test_learn_jacobian_error_shrinks_with_more_samples() -> None:
    """With noise on E the least-squares J is unbiased and its error falls like 1/√N_s."""
    rng = np.random.default_rng(1)
    J_true = rng.normal(size=(40, 6)) * [300, 300, 300, 20, 20, 5]

    def mean_error(n: int) -> float:
        errs = []
        for _ in range(30):
            B = _design(rng, n)
            E = J_true @ B + rng.normal(scale=0.1, size=(40, n))
            errs.append(np.linalg.norm((learn_jacobian(E, B) - J_true) @ B) / np.sqrt(n))
        return float(np.mean(errs))

    e12, e48, e192 = mean_error(12), mean_error(48), mean_error(192)
    assert e48 < 0.7 * e12 and e192 < 0.7 * e48


def test_learn_jacobian_checks_shapes() -> None:
    with pytest.raises(ValueError, match="6, n"):
        learn_jacobian(np.zeros((4, 10)), np.zeros((5, 10)))
    with pytest.raises(ValueError):
        learn_jacobian(np.zeros((4, 9)), np.zeros((6, 10)))


def test_per_feature_fit_uses_the_views_each_feature_was_tracked_in() -> None:
    rng = np.random.default_rng(2)
    n, k = 20, 30
    B = _design(rng, n)
    J_true = rng.normal(size=(2 * k, 6)) * [300, 300, 300, 20, 20, 5]
    E = J_true @ B
    need = max(7, int(np.ceil(0.6 * n)))  # 12 of 20 views
    seen_counts = rng.integers(0, n + 1, size=k)
    seen_counts[:4] = [n, need, need - 1, 0]
    for f, count in enumerate(seen_counts):
        lost = rng.choice(n, n - count, replace=False)
        E[2 * f + rng.integers(2), lost] = np.nan  # losing u or v alone loses the view
    J, ok = learn_jacobian_per_feature(E, B)
    np.testing.assert_array_equal(ok, seen_counts >= need)
    rows = np.repeat(ok, 2)
    np.testing.assert_allclose(J[rows], J_true[rows], rtol=1e-7, atol=1e-6)
    assert np.isnan(J[~rows]).all()


def test_per_feature_fit_flags_a_feature_whose_views_do_not_span_the_pose() -> None:
    """Enough views, but all of them perturbations along one direction: no 6-D fit."""
    rng = np.random.default_rng(3)
    n = 24
    B = _design(rng, n)
    B[:, :12] = np.outer(B[:, 0], rng.uniform(0.5, 1.5, 12))  # 12 views along one direction
    J_true = rng.normal(size=(4, 6)) * 100
    E = J_true @ B
    E[2:, 15:] = np.nan  # feature 1: the 12 degenerate views and 3 more, 15 ≥ 60 % of 24
    assert np.isfinite(E[2]).sum() >= 0.6 * n
    J, ok = learn_jacobian_per_feature(E, B)
    assert ok.tolist() == [True, False]
    np.testing.assert_allclose(J[:2], J_true[:2], rtol=1e-7)


# -- sampling perturbations ---------------------------------------------------------------
def _axes_angles(B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Active rotation axes and angles of B's rotation rows (the paper's q = −tan(θ/2)·axis)."""
    q = B[:3].T
    norm = np.linalg.norm(q, axis=1)
    return -q / norm[:, None], 2 * np.arctan(norm)


def test_perturbations_span_all_six_axes_within_their_bounds() -> None:
    rng = np.random.default_rng(4)
    cap = np.radians(2.0)
    for n in (6, 12, 24):
        B = sample_perturbations(rng, n, cap, HALF_WIDTH)
        assert B.shape == (6, n)
        assert np.linalg.matrix_rank(B) == 6
        assert design_condition(B) < MAX_DESIGN_CONDITION
        _, angles = _axes_angles(B)
        assert (angles <= cap + 1e-12).all()
        assert (np.abs(B[3:]) <= HALF_WIDTH[:, None]).all()
        for i in range(n):  # each column is the increment of a rotation by that angle
            R = gibbs_to_matrix(B[:3, i])
            assert rotation_error_deg(np.eye(3), R) == pytest.approx(np.degrees(angles[i]))


def test_perturbation_axes_stay_in_the_cone() -> None:
    rng = np.random.default_rng(5)
    centre = np.array([1.0, 2.0, -2.0]) / 3.0
    cone = np.radians(30.0)
    B = sample_perturbations(rng, 128, np.radians(1.0), HALF_WIDTH, axis=centre, cone_rad=cone)
    axes, _ = _axes_angles(B)
    off_axis = np.arccos(np.clip(axes @ centre, -1, 1))
    assert off_axis.max() <= cone + 1e-9
    assert off_axis.max() > 0.8 * cone  # and fill it
    # Without a cone the axes cover the whole sphere.
    B = sample_perturbations(rng, 128, np.radians(1.0), HALF_WIDTH)
    axes, _ = _axes_angles(B)
    assert (axes @ centre).min() < -0.8 and (axes @ centre).max() > 0.8


def test_cap_angles_follow_uniform_rotations() -> None:
    """Uniform rotations restricted to a cap: pdf ∝ sin²(a/2), mean ≈ 3θ/4 for small θ."""
    rng = np.random.default_rng(6)
    cap = np.radians(5.0)
    a = sample_cap_angles(rng, 20000, cap)
    assert a.min() >= 0 and a.max() <= cap
    assert a.mean() == pytest.approx(0.75 * cap, rel=0.01)
    assert np.median(a) == pytest.approx(cap * 0.5 ** (1 / 3), rel=0.01)


def test_design_condition_flags_a_design_that_misses_an_axis() -> None:
    rng = np.random.default_rng(7)
    B = _design(rng, 24)
    B[5] = 0.5 * B[3] - 2.0 * B[4]  # forward motion tied to the lateral ones
    assert design_condition(B) > 1e6 * MAX_DESIGN_CONDITION


# -- LM on a linear model ------------------------------------------------------------------
def test_one_undamped_lm_step_solves_an_exactly_linear_problem() -> None:
    rng = np.random.default_rng(8)
    J = rng.normal(size=(40, 6)) * [300, 300, 300, 20, 20, 5]
    dp_true = rng.normal(size=6) * [1e-2, 1e-2, 1e-2, 0.1, 0.1, 1.0]
    r = J @ dp_true
    # (lm_step adds a 1e-12·tr(A) ridge for safety: a relative effect of ~1e-8)
    np.testing.assert_allclose(lm_step(J, r, 0.0), dp_true, rtol=1e-6)
    w = rng.uniform(0.2, 1.0, 20)
    np.testing.assert_allclose(lm_step(J, r, 0.0, w), dp_true, rtol=1e-6)


def test_damping_shortens_the_step_and_keeps_it_downhill() -> None:
    rng = np.random.default_rng(9)
    J = rng.normal(size=(40, 6))
    r = rng.normal(size=40)
    g = J.T @ r
    norms = []
    for lam in (0.0, 1e-2, 1.0, 1e2, 1e4):
        dp = lm_step(J, r, lam)
        assert g @ dp > 0  # a descent direction of ½‖r − J δp‖²
        assert weighted_cost(r - J @ dp) < weighted_cost(r)
        norms.append(np.linalg.norm(dp))
    assert all(a > b for a, b in zip(norms, norms[1:], strict=False))


# -- the signs of docs/method.md on a real projection -------------------------------------
CAMERA = PinholeCamera(640, 480, 800.0, 820.0, 330.0, 235.0, 2.0)


def _project(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Feature positions stacked (u₁, v₁, u₂, v₂, …) of model points at pose (R, t)."""
    return CAMERA.project(points @ R.T + t).ravel()


def _lm_on_projection(
    steps: int, flip_translation: bool = False
) -> tuple[list[float], list[float], float]:
    """Learn J from perturbed 'renders' (projections) and take LM steps, as the estimator does.

    Returns per-step rotation errors (deg), translation errors, and the range.
    """
    rng = np.random.default_rng(10)
    points = rng.uniform(-1.0, 1.0, size=(30, 3))
    R_true = axis_angle_to_matrix(np.array([0.3, -0.5, 0.8]), 0.9)
    t_true = np.array([0.2, -0.3, 10.0])
    x_ref = _project(points, R_true, t_true)
    R = R_true @ axis_angle_to_matrix(np.array([1.0, 1.0, 0.0]), np.radians(3.0))
    t = t_true + np.array([0.15, -0.1, 0.25])  # 3 % of the range
    rot, tra = [rotation_error_deg(R_true, R)], [float(np.linalg.norm(t - t_true))]
    for _ in range(steps):
        x_hat = _project(points, R, t)
        B = sample_perturbations(rng, 12, np.radians(0.5), np.array([0.03, 0.03, 0.1]))
        E = np.column_stack(
            [_project(points, *apply_increment(R, t, B[:, i])) - x_hat for i in range(12)]
        )
        J = learn_jacobian(E, B)
        dp = lm_step(J, x_ref - x_hat, 1e-6)
        if flip_translation:  # the paper's Δt = t_ref − t_i read with p ← p + δp
            dp[3:] = -dp[3:]
        R, t = apply_increment(R, t, dp)
        rot.append(rotation_error_deg(R_true, R))
        tra.append(float(np.linalg.norm(t - t_true)))
    return rot, tra, float(np.linalg.norm(t_true))


def test_learned_jacobian_lm_converges_on_a_pinhole_projection() -> None:
    rot, tra, range_ = _lm_on_projection(steps=6)
    assert rot[1] < 0.1 * rot[0] and tra[1] < 0.1 * tra[0]  # the first step is the right way
    assert rot[-1] < 1e-6 and tra[-1] < 1e-8 * range_


def test_sign_error_in_the_translation_update_is_caught() -> None:
    """Control: the mixed-up convention docs/method.md warns about walks away from the answer."""
    rot, tra, _ = _lm_on_projection(steps=3, flip_translation=True)
    assert tra[1] > tra[0]


# -- robust weights, RANSAC and covariance ---------------------------------------------------
def _linear_problem_with_outliers(
    seed: int, k: int = 60, n_out: int = 12
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(2 * k, 6)) * [300, 300, 300, 20, 20, 5]
    dp_true = rng.normal(size=6) * [1e-3, 1e-3, 1e-3, 0.02, 0.02, 0.1]
    r = J @ dp_true + rng.normal(scale=0.1, size=2 * k)
    out = rng.choice(k, n_out, replace=False)
    offsets = rng.normal(size=(n_out, 2))
    offsets *= rng.uniform(3.0, 20.0, (n_out, 1)) / np.linalg.norm(offsets, axis=1, keepdims=True)
    r.reshape(-1, 2)[out] += offsets
    is_out = np.zeros(k, dtype=bool)
    is_out[out] = True
    return J, r, dp_true, is_out


def test_ransac_rejects_injected_outliers() -> None:
    for seed in range(5):
        J, r, _, is_out = _linear_problem_with_outliers(seed)
        inliers = ransac_increment(J, r, np.random.default_rng(seed), threshold_px=1.0)
        np.testing.assert_array_equal(inliers, ~is_out)


def test_irls_down_weights_outliers_and_recovers_the_increment() -> None:
    for seed in range(5):
        J, r, dp_true, is_out = _linear_problem_with_outliers(seed)
        dp, w, scale = irls_increment(J, r)
        assert w[is_out].max() < 0.05
        assert w[~is_out].min() > 0.15 and w[~is_out].mean() > 0.7
        assert 0.05 <= scale < 0.3  # noise σ = 0.1 px per coordinate
        plain = lm_step(J, r, 0.0)
        scale_dp = np.array([1e-3, 1e-3, 1e-3, 0.02, 0.02, 0.1])
        assert np.linalg.norm((dp - dp_true) / scale_dp) < 0.2 * np.linalg.norm(
            (plain - dp_true) / scale_dp
        )


def test_the_robust_scale_floor_keeps_features_a_tight_fit_would_drop() -> None:
    """Most features fit to 0.03 px, a few are 0.5 px out (what a direction only they see
    leaves): at the estimate's floor (0.05 px) Tukey drops them, at a tracker's (0.3 px) they
    keep most of their weight and the others keep theirs."""
    from worker.align.tracker import TRACK_ROBUST_FLOOR_PX

    rng = np.random.default_rng(3)
    k = 60
    J = rng.normal(size=(2 * k, 6)) * [300, 300, 300, 20, 20, 5]
    r = rng.normal(scale=0.03, size=2 * k)
    few = np.zeros(k, dtype=bool)
    few[:6] = True
    r.reshape(-1, 2)[few] += 0.5 / np.sqrt(2)
    _, w_tight, scale_tight = irls_increment(J, r)
    _, w_floor, scale_floor = irls_increment(J, r, floor=TRACK_ROBUST_FLOOR_PX)
    assert scale_tight < 0.1 and w_tight[few].max() < 0.05
    assert scale_floor == TRACK_ROBUST_FLOOR_PX and w_floor[few].min() > 0.5
    assert w_floor[~few].min() > 0.95


def test_covariance_matches_the_analytic_one_on_a_linear_gaussian_problem() -> None:
    """Monte Carlo: the spread of the fitted δp is σ² (JᵀJ)⁻¹, and so is what covariance()
    reports from the residuals of one fit."""
    rng = np.random.default_rng(11)
    k, sigma = 80, 0.3
    J = rng.normal(size=(2 * k, 6)) * [300, 300, 300, 20, 20, 5]
    w = np.ones(k)
    analytic = sigma**2 * np.linalg.inv(J.T @ J)
    L_inv = np.linalg.inv(np.linalg.cholesky(analytic))
    dp_true = rng.normal(size=6) * 1e-2
    fits, reported, sigmas = [], [], []
    for _ in range(2000):
        r = J @ dp_true + rng.normal(scale=sigma, size=2 * k)
        dp = lm_step(J, r, 0.0, w)
        C, s = covariance(J, r - J @ dp, w)
        fits.append(dp)
        reported.append(C)
        sigmas.append(s)
    empirical = np.cov(np.array(fits).T)
    np.testing.assert_allclose(L_inv @ empirical @ L_inv.T, np.eye(6), atol=0.1)
    np.testing.assert_allclose(L_inv @ np.mean(reported, axis=0) @ L_inv.T, np.eye(6), atol=0.03)
    assert np.mean(sigmas) == pytest.approx(sigma, rel=0.02)


def test_covariance_counts_errors_shared_by_nearby_features_once() -> None:
    """Features in one image cell share an error (one edge, one shading difference): the
    independent-error covariance then understates the spread of δp; the cluster-robust one,
    given the features' positions, matches it."""
    rng = np.random.default_rng(5)
    cell = 48.0
    centres = rng.uniform(0, 480, size=(40, 2))  # 40 regions, 8 features each, within a cell
    x = np.repeat(np.floor(centres / cell) * cell + 10.0, 8, axis=0) + rng.uniform(0, 20, (320, 2))
    k = len(x)
    _, region = np.unique(np.floor(x / cell), axis=0, return_inverse=True)
    region = region.ravel()
    # The image Jacobian of points (interaction matrix, f = 500 px): smooth across the image,
    # so nearby features respond alike and an error they share does not average out.
    f = 500.0
    u, v = ((x - 240.0) / f).T
    inv_z = 1.0 / (10.0 + 2.0 * np.sin(u * 3.0))
    zero = np.zeros(k)
    Ju = np.stack([-inv_z, zero, u * inv_z, u * v, -(1 + u**2), v], axis=1)
    Jv = np.stack([zero, -inv_z, v * inv_z, 1 + v**2, -u * v, -u], axis=1)
    J = f * np.stack([Ju, Jv], axis=1).reshape(2 * k, 6)
    w = np.ones(k)
    fits, plain, robust = [], [], []
    for _ in range(600):
        shared = rng.normal(scale=0.3, size=(region.max() + 1, 2))[region]  # per region
        r = (shared + rng.normal(scale=0.05, size=(k, 2))).ravel()
        dp = lm_step(J, r, 0.0, w)
        fits.append(dp)
        plain.append(covariance(J, r - J @ dp, w)[0])
        robust.append(covariance(J, r - J @ dp, w, x, cell_px=cell)[0])
    empirical = np.trace(np.cov(np.array(fits).T) @ J.T @ J)
    plain_ratio = np.trace(np.mean(plain, axis=0) @ J.T @ J) / empirical
    robust_ratio = np.trace(np.mean(robust, axis=0) @ J.T @ J) / empirical
    assert plain_ratio < 0.2  # measured 0.07: counts every feature as independent
    assert 0.6 < robust_ratio < 1.3  # measured 0.81 (the sandwich runs a little low)
