"""Pose math (worker/engine/posemath.py): the paper's Cayley/Gibbs map, quaternions, axis-angle,
local increments and the schema conversions. Pure numpy, seeded."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import polar

from schemas.pose import Pose
from worker.engine.exceptions import InvalidPoseError
from worker.engine.posemath import (
    apply_increment,
    axis_angle_to_matrix,
    gibbs_to_matrix,
    increment_between,
    matrix_to_axis_angle,
    matrix_to_gibbs,
    matrix_to_quaternion,
    matrix_to_rotvec,
    orthonormalize,
    pose_from_schema,
    pose_to_schema,
    quaternion_to_matrix,
    rotvec_to_matrix,
    skew,
    step_norm,
    vee,
)

N_CASES = 200
I3 = np.eye(3)


def rotation_angle(R: np.ndarray) -> float:
    """Rotation angle of R in radians, in [0, π]."""
    return matrix_to_axis_angle(R)[1]


def random_rotations(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Uniform random rotations (from normalised Gaussian quaternions, built independently of
    the code under test with Rodrigues' formula)."""
    out = []
    for _ in range(n):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.0, np.pi)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        out.append(I3 + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K)
    return out


def assert_rotation(R: np.ndarray) -> None:
    np.testing.assert_allclose(R.T @ R, I3, atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
gibbs_vectors = st.lists(finite, min_size=3, max_size=3).map(np.array)


# -- skew / vee ---------------------------------------------------------------------------
def test_skew_is_the_cross_product_and_vee_inverts_it() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        v, w = rng.normal(size=(2, 3))
        np.testing.assert_allclose(skew(v) @ w, np.cross(v, w), atol=1e-14)
        np.testing.assert_allclose(vee(skew(v)), v, atol=1e-14)
        np.testing.assert_allclose(skew(v).T, -skew(v))


@pytest.mark.parametrize("bad", [np.zeros(2), np.zeros(4), np.zeros((3, 1))])
def test_shape_errors_name_the_shape(bad: np.ndarray) -> None:
    with pytest.raises(InvalidPoseError, match=r"shape \(3,\)"):
        skew(bad)
    with pytest.raises(InvalidPoseError, match=r"shape \(3, 3\)"):
        matrix_to_gibbs(np.zeros((3, 4)))
    with pytest.raises(InvalidPoseError, match=r"shape \(6,\)"):
        apply_increment(I3, np.zeros(3), np.zeros(5))


# -- Cayley / Gibbs -----------------------------------------------------------------------
@settings(max_examples=300, derandomize=True, deadline=None)
@given(gibbs_vectors)
def test_gibbs_closed_form_equals_the_papers_inverse_form(q: np.ndarray) -> None:
    """R = (I + [q×])⁻¹ (I − [q×]) (the paper) equals the closed form used by the code."""
    S = skew(q)
    R_paper = np.linalg.solve(I3 + S, I3 - S)
    R = gibbs_to_matrix(q)
    np.testing.assert_allclose(R, R_paper, atol=1e-10)
    assert_rotation(R)
    # (I − [q×])(I + [q×])⁻¹ is the same matrix: the two factors commute.
    np.testing.assert_allclose(R, (I3 - S) @ np.linalg.inv(I3 + S), atol=1e-10)


def test_gibbs_sign_convention_is_the_papers() -> None:
    """The paper's q is minus the active tan(θ/2)·axis, and R ≈ I − 2[q×] for small q."""
    rng = np.random.default_rng(1)
    for R in random_rotations(rng, 50):
        axis, angle = matrix_to_axis_angle(R)
        np.testing.assert_allclose(matrix_to_gibbs(R), -np.tan(angle / 2) * axis, atol=1e-9)
    q = 1e-6 * rng.normal(size=3)
    np.testing.assert_allclose(gibbs_to_matrix(q), I3 - 2 * skew(q), atol=1e-11)


def test_gibbs_round_trip() -> None:
    rng = np.random.default_rng(2)
    for R in random_rotations(rng, N_CASES):
        if rotation_angle(R) > np.radians(179.0):
            continue
        np.testing.assert_allclose(gibbs_to_matrix(matrix_to_gibbs(R)), R, atol=1e-10)
    for _ in range(N_CASES):
        q = rng.normal(size=3) * 10 ** rng.uniform(-6, 2)
        np.testing.assert_allclose(matrix_to_gibbs(gibbs_to_matrix(q)), q, rtol=1e-8, atol=1e-14)


@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, -2, 0.5)])
def test_matrix_to_gibbs_raises_at_180_degrees(axis: tuple[float, ...]) -> None:
    R = axis_angle_to_matrix(np.array(axis, float), np.pi)
    with pytest.raises(InvalidPoseError, match="180"):
        matrix_to_gibbs(R)
    # Just short of 180° it is large but finite and still inverts.
    R = axis_angle_to_matrix(np.array(axis, float), np.pi - 1e-3)
    q = matrix_to_gibbs(R)
    assert 1e3 < np.linalg.norm(q) < 1e4
    np.testing.assert_allclose(gibbs_to_matrix(q), R, atol=1e-9)


# -- quaternions --------------------------------------------------------------------------
def test_quaternion_matches_axis_angle() -> None:
    """[w, x, y, z] = [cos(θ/2), sin(θ/2)·axis] is the active rotation by θ about axis."""
    rng = np.random.default_rng(3)
    for _ in range(N_CASES):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0, np.pi)
        quat = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
        R = quaternion_to_matrix(quat)
        np.testing.assert_allclose(R, axis_angle_to_matrix(axis, angle), atol=1e-12)
        np.testing.assert_allclose(R @ axis, axis, atol=1e-12)  # axis is fixed
        np.testing.assert_allclose(quaternion_to_matrix(-quat), R, atol=1e-12)  # q ≡ −q


def test_quaternion_round_trips_every_shepperd_branch() -> None:
    rng = np.random.default_rng(4)
    cases = [rng.normal(size=4) for _ in range(N_CASES)]
    # Near 180° about each axis: trace < 0, and each of R00, R11, R22 the largest in turn.
    for k in range(3):
        for angle in (np.pi, np.pi - 1e-8, np.pi - 0.3):
            axis = np.eye(3)[k] + 0.05 * rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            cases.append(np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis]))
    for quat in cases:
        quat = quat / np.linalg.norm(quat)
        quat = quat if quat[0] >= 0 else -quat
        R = quaternion_to_matrix(quat)
        assert_rotation(R)
        back = matrix_to_quaternion(R)
        assert back[0] >= 0
        if quat[0] < 1e-6:  # at exactly 180° q and −q both have w = 0
            back = back * np.sign(back @ quat)
        np.testing.assert_allclose(back, quat, atol=1e-10)


def test_quaternion_input_checks() -> None:
    with pytest.raises(InvalidPoseError):
        quaternion_to_matrix([0, 0, 0, 0])
    with pytest.raises(InvalidPoseError):
        quaternion_to_matrix([np.nan, 0, 0, 1])
    with pytest.raises(InvalidPoseError):
        quaternion_to_matrix([1, 0, 0])
    # A non-unit quaternion is normalised, not scaled into the matrix.
    np.testing.assert_allclose(quaternion_to_matrix([2.0, 0, 0, 0]), I3)


# -- axis-angle ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    "angle",
    [0.0, 1e-12, 1e-8, 1e-4, 0.5, 2.0, np.pi - 1e-2, np.pi - 1e-5, np.pi - 1e-8, np.pi],
)
def test_axis_angle_round_trip_near_0_and_180(angle: float) -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = axis_angle_to_matrix(axis, angle)
        axis_back, angle_back = matrix_to_axis_angle(R)
        # arccos((tr R − 1)/2) would lose ~1e-8 rad here; the quaternion route must not.
        assert angle_back == pytest.approx(angle, abs=1e-9)
        if angle > 1e-7:
            if angle == np.pi:
                axis_back = axis_back * np.sign(axis_back @ axis)  # ±axis are the same rotation
            np.testing.assert_allclose(axis_back, axis, atol=1e-6)
        np.testing.assert_allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-9)


def test_rotvec_zero_is_identity() -> None:
    np.testing.assert_array_equal(rotvec_to_matrix(np.zeros(3)), I3)
    np.testing.assert_array_equal(matrix_to_rotvec(I3), np.zeros(3))


# -- orthonormalize -----------------------------------------------------------------------
def test_orthonormalize_is_the_nearest_rotation() -> None:
    rng = np.random.default_rng(6)
    for R in random_rotations(rng, 50):
        M = R + 1e-3 * rng.normal(size=(3, 3))
        U, _ = polar(M)  # nearest orthogonal matrix (det +1 here: M is near a rotation)
        Rn = orthonormalize(M)
        assert_rotation(Rn)
        np.testing.assert_allclose(Rn, U, atol=1e-12)
        np.testing.assert_allclose(orthonormalize(R), R, atol=1e-12)


def test_orthonormalize_never_returns_a_reflection() -> None:
    rng = np.random.default_rng(7)
    for R in random_rotations(rng, 20):
        Rn = orthonormalize(R @ np.diag([1.0, 1.0, -1.0]))
        assert_rotation(Rn)


# -- local increments ---------------------------------------------------------------------
def test_apply_increment_follows_method_md() -> None:
    """R ← R·C(δq), t ← t + δt."""
    rng = np.random.default_rng(8)
    for R in random_rotations(rng, 20):
        t, dp = rng.normal(size=3), rng.normal(size=6) * 0.1
        R1, t1 = apply_increment(R, t, dp)
        np.testing.assert_allclose(R1, R @ gibbs_to_matrix(dp[:3]), atol=1e-14)
        np.testing.assert_allclose(t1, t + dp[3:], atol=1e-14)


def test_increment_round_trip() -> None:
    rng = np.random.default_rng(9)
    Rs = random_rotations(rng, 2 * N_CASES)
    for R0, R1 in zip(Rs[::2], Rs[1::2], strict=True):
        t0, t1 = rng.normal(size=(2, 3)) * 10
        if rotation_angle(R0.T @ R1) > np.radians(179.0):
            continue
        dp = increment_between(R0, t0, R1, t1)
        R, t = apply_increment(R0, t0, dp)
        np.testing.assert_allclose(R, R1, atol=1e-9)
        np.testing.assert_allclose(t, t1, atol=1e-12)
    for R0 in Rs[:50]:
        dp = rng.normal(size=6) * 0.2
        R, t = apply_increment(R0, np.ones(3), dp)
        np.testing.assert_allclose(increment_between(R0, np.ones(3), R, t), dp, atol=1e-10)


@pytest.mark.parametrize("start_deg", [179.9, 180.0])
def test_local_increments_work_at_attitudes_near_180_degrees(start_deg: float) -> None:
    """The absolute attitude at ~180° has no Gibbs vector, but a local increment does: an
    attitude at 179.9° plus a small increment (one that carries it through 180°, too)."""
    rng = np.random.default_rng(10)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R0 = axis_angle_to_matrix(axis, np.radians(start_deg))
        t0 = np.array([0.1, -0.2, 20.0])
        for dq in (1e-3 * rng.normal(size=3), -np.tan(np.radians(0.25)) * axis):
            dp = np.concatenate([dq, [0.01, 0.0, -0.1]])
            R1, t1 = apply_increment(R0, t0, dp)
            assert_rotation(R1)
            np.testing.assert_allclose(increment_between(R0, t0, R1, t1), dp, atol=1e-10)
            # The step is the rotation it claims: 2·atan|δq| away from R0.
            assert rotation_angle(R0.T @ R1) == pytest.approx(
                2 * np.arctan(np.linalg.norm(dq)), abs=1e-10
            )
        # +0.25° about the axis carries 179.9° to 180.15°, i.e. 179.85° about −axis.
        R2 = R0 @ gibbs_to_matrix(-np.tan(np.radians(0.125)) * axis)
        assert np.degrees(rotation_angle(R2)) == pytest.approx(360 - start_deg - 0.25, abs=1e-8)


def test_step_norm_units() -> None:
    """[rotation angle (rad), δt / range] combined in quadrature."""
    q = -np.tan(np.radians(0.3) / 2) * np.array([0.0, 0.6, 0.8])
    dp = np.concatenate([q, [0.0, 0.4, 0.3]])  # 0.3° and 0.5 units at a range of 100
    expected = np.hypot(np.radians(0.3), 0.5 / 100)
    assert step_norm(dp, 100.0) == pytest.approx(expected, rel=1e-12)


# -- schema conversions -------------------------------------------------------------------
def test_pose_from_schema_agrees_for_every_attitude_form() -> None:
    rng = np.random.default_rng(12)
    for R in random_rotations(rng, 50):
        if rotation_angle(R) > np.radians(179.0):
            continue
        t = [0.5, -1.0, 30.0]
        forms = {
            "R": Pose(t=t, R=R.tolist()),
            "quaternion": Pose(t=t, quaternion=matrix_to_quaternion(R).tolist()),
            "q": Pose(t=t, q=matrix_to_gibbs(R).tolist()),
        }
        for name, pose in forms.items():
            R_got, t_got = pose_from_schema(pose)
            np.testing.assert_allclose(R_got, R, atol=1e-9, err_msg=name)
            np.testing.assert_array_equal(t_got, t)


def test_pose_from_schema_orthonormalises_a_slightly_off_matrix() -> None:
    R = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), 0.7)
    noisy = R + 2e-4 * np.random.default_rng(13).normal(size=(3, 3))
    R_got, _ = pose_from_schema(Pose(t=[0, 0, 5], R=noisy.tolist()))
    assert_rotation(R_got)
    np.testing.assert_allclose(R_got, R, atol=1e-3)


def test_pose_to_schema_round_trip() -> None:
    rng = np.random.default_rng(14)
    for R in random_rotations(rng, 50):
        t = rng.normal(size=3) + [0, 0, 50]
        out = pose_to_schema(R, t)
        np.testing.assert_allclose(out.R, R, atol=1e-12)
        np.testing.assert_allclose(out.t, t)
        np.testing.assert_allclose(quaternion_to_matrix(out.quaternion), R, atol=1e-12)
        assert out.quaternion[0] >= 0
        np.testing.assert_allclose(gibbs_to_matrix(out.q), R, atol=1e-8)
        for form in ("R", "quaternion", "q"):
            again = Pose(t=out.t, **{form: getattr(out, form)})
            np.testing.assert_allclose(pose_from_schema(again)[0], R, atol=1e-8)


@pytest.mark.parametrize("angle_deg", [180.0, 180.0 - 1e-3, 179.99])
def test_pose_to_schema_q_near_180_degrees_is_usable(angle_deg: float) -> None:
    """Near 180° q is huge; what is reported must still be finite, accepted by the schema and
    mean (almost) the same rotation — not, say, zero (the identity)."""
    axis = np.array([0.36, 0.48, 0.8])
    R = axis_angle_to_matrix(axis, np.radians(angle_deg))
    out = pose_to_schema(R, [0, 0, 10])
    assert np.isfinite(out.q).all()
    np.testing.assert_allclose(quaternion_to_matrix(out.quaternion), R, atol=1e-12)
    np.testing.assert_allclose(gibbs_to_matrix(out.q), R, atol=1e-5)
    R_back, _ = pose_from_schema(Pose(t=out.t, q=out.q))
    np.testing.assert_allclose(R_back, R, atol=1e-5)
