"""Learning the feature-to-pose Jacobian from perturbed renders (docs/method.md, steps 2–4).

Pose increments are local: a perturbation Δp = [Δq, Δt] makes R_i = R̂·C(Δq), t_i = t̂ + Δt.
Columns of B are the Δp_i (6 × N_s); columns of E are the feature displacements they caused,
x_i − x̂ (m × N_s, m = 2 × features, rows u₁, v₁, u₂, v₂, …). Then E = J B in least squares:
J = E Bᵀ (B Bᵀ)⁻¹.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.posemath import axis_angle_to_matrix, matrix_to_gibbs

Array = NDArray[np.float64]

#: Largest condition number accepted for the row-standardised B Bᵀ.
MAX_DESIGN_CONDITION = 50.0
#: A feature needs tracks in at least this fraction of the views (and ≥ 7) for its own rows.
MIN_VIEW_FRACTION = 0.6


def sample_cap_angles(rng: np.random.Generator, n: int, max_angle_rad: float) -> Array:
    """Angles in [0, θ] distributed as for uniform random rotations in a cap (pdf ∝ sin²(a/2))."""
    grid = np.linspace(0.0, max_angle_rad, 1025)
    cdf = grid - np.sin(grid)  # ∫ 2 sin²(a/2) da
    return np.interp(rng.uniform(0.0, cdf[-1], n), cdf, grid)


def sample_axes(rng: np.random.Generator, n: int, centre: Array | None, cone_rad: float) -> Array:
    """Unit axes (n, 3) uniform on the sphere, or in a cone of half-angle ``cone_rad``."""
    if centre is None or cone_rad >= np.pi:
        v = rng.normal(size=(n, 3))
        return v / np.linalg.norm(v, axis=1, keepdims=True)
    cos_min = np.cos(cone_rad)
    z = rng.uniform(cos_min, 1.0, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1.0 - z * z)
    local = np.column_stack([s * np.cos(phi), s * np.sin(phi), z])
    c = centre / np.linalg.norm(centre)
    helper = np.array([1.0, 0.0, 0.0]) if abs(c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, c)
    x /= np.linalg.norm(x)
    return local @ np.column_stack([x, np.cross(c, x), c]).T


def sample_perturbations(
    rng: np.random.Generator,
    n: int,
    max_angle_rad: float,
    trans_half_width: Array,
    axis: Array | None = None,
    cone_rad: float = np.pi,
) -> Array:
    """B (6, n): rotations in a cap (axes in a cone around ``axis``), translations in a box.

    Re-draws until the row-standardised design spans all six axes with a bounded condition
    number (a rank-deficient B makes B Bᵀ singular).
    """
    for _ in range(50):
        axes = sample_axes(rng, n, axis, cone_rad)
        angles = sample_cap_angles(rng, n, max_angle_rad)
        dq = np.array(
            [
                matrix_to_gibbs(axis_angle_to_matrix(a, th))
                for a, th in zip(axes, angles, strict=True)
            ]
        )
        dt = rng.uniform(-1.0, 1.0, size=(n, 3)) * trans_half_width
        B = np.column_stack([dq, dt]).T
        if design_condition(B) < MAX_DESIGN_CONDITION:
            return B
    raise TooFewFeaturesError("could not draw perturbations spanning all six pose axes")


def design_condition(B: Array) -> float:
    """Condition number of B Bᵀ after scaling each row of B to unit RMS."""
    Bs = B / np.sqrt(np.mean(B**2, axis=1, keepdims=True))
    return float(np.linalg.cond(Bs @ Bs.T))


def learn_jacobian(E: Array, B: Array) -> Array:
    """J = E Bᵀ (B Bᵀ)⁻¹, shape (m, 6), solved with B's rows standardised for conditioning."""
    E = np.asarray(E, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if B.shape[0] != 6 or E.shape[1] != B.shape[1]:
        raise ValueError(f"need E (m, n) and B (6, n), got {E.shape} and {B.shape}")
    s = np.sqrt(np.mean(B**2, axis=1))
    Bs = B / s[:, None]
    Js = np.linalg.solve(Bs @ Bs.T, Bs @ E.T).T
    return Js / s[None, :]


def learn_jacobian_per_feature(
    E: Array, B: Array, min_fraction: float = MIN_VIEW_FRACTION
) -> tuple[Array, NDArray[np.bool_]]:
    """Each feature's two rows fitted from the views in which it was tracked.

    E (m, n) holds NaN where a feature was lost. Returns J (m, 6) and a per-feature mask (m/2,)
    of features with enough views (≥ max(7, min_fraction·n)) for a well-posed fit.
    """
    m, n = E.shape
    seen = np.isfinite(E[0::2]) & np.isfinite(E[1::2])  # (k, n)
    enough = seen.sum(axis=1) >= max(7, int(np.ceil(min_fraction * n)))
    s = np.sqrt(np.mean(B**2, axis=1))
    Bs = B / s[:, None]
    W = seen.astype(np.float64)
    G = np.einsum("ij,kj,lj->kil", Bs, W, Bs)  # (k, 6, 6): Σ_views b bᵀ
    E0 = np.nan_to_num(E)
    rhs_u = np.einsum("ij,kj->ki", Bs, E0[0::2] * W)  # (k, 6)
    rhs_v = np.einsum("ij,kj->ki", Bs, E0[1::2] * W)
    J = np.full((m, 6), np.nan)
    ok = enough.copy()
    conds = np.linalg.cond(G[enough]) if enough.any() else np.zeros(0)
    ok[np.flatnonzero(enough)[conds > 1e4]] = False
    if ok.any():
        Gi = np.linalg.inv(G[ok])
        J[0::2][ok] = np.einsum("kij,kj->ki", Gi, rhs_u[ok]) / s
        J[1::2][ok] = np.einsum("kij,kj->ki", Gi, rhs_v[ok]) / s
    return J, ok
