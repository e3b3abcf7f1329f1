"""Levenberg–Marquardt steps and pose-consistent outlier rejection on the learned linear model.

Residuals are r = x̃ − x̂ (reference minus render, px), stacked (u₁, v₁, u₂, v₂, …); the model
is r ≈ J δp. Per-feature weights w (one per feature, applied to both its rows) come from IRLS
with Tukey's biweight, and a RANSAC over δp rejects features that no single pose explains.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: Tukey biweight tuning constant (95 % efficiency), in robust standard deviations.
TUKEY_C = 4.685
#: Features drawn per RANSAC hypothesis.
RANSAC_SET_SIZE = 6
#: Floor of the robust residual scale, px: KLT cannot resolve motion below this.
MIN_SCALE_PX = 0.05
#: Smallest LM damping λ.
LAMBDA_MIN = 1e-9
#: An accepted step counts as not shrinking when it is more than this fraction of the last.
SLOW_RATIO = 0.5


#: Image cell (px) within which feature errors are taken as one, for the covariance.
CLUSTER_CELL_PX = 48.0
#: Fewest cells for the cluster-robust covariance (below: the independent-error one).
MIN_CLUSTERS = 10


def expand(w: Array) -> Array:
    """Per-feature weights (k,) to per-row weights (2k,)."""
    return np.repeat(w, 2)


def lm_step(J: Array, r: Array, lam: float, w: Array | None = None) -> Array:
    """δp = (JᵀWJ + λ diag(JᵀWJ))⁻¹ JᵀW r, shape (n,) for J (2k, n). ``w`` is per feature
    (k,) or None."""
    Wr = expand(w) if w is not None else np.ones(len(r))
    JtW = J.T * Wr
    A = JtW @ J
    g = JtW @ r
    D = np.diag(np.diag(A))
    return np.linalg.solve(A + lam * D + 1e-12 * np.eye(len(A)) * np.trace(A), g)


def feature_norms(r: Array) -> Array:
    """Per-feature residual lengths ‖(u, v)‖, shape (k,)."""
    return np.hypot(r[0::2], r[1::2])


def robust_scale(norms: Array, floor: float = MIN_SCALE_PX) -> float:
    """A robust standard deviation of 2-D residuals from their lengths (MAD-like), px, at
    least ``floor``."""
    if len(norms) == 0:
        return floor
    # For isotropic Gaussian errors ‖e‖ is Rayleigh(σ) with median σ·√(2 ln 2).
    return max(float(np.median(norms)) / np.sqrt(2 * np.log(2)), floor)


def tukey_weights(norms: Array, scale: float) -> Array:
    """Tukey biweight per feature: (1 − (e/cσ)²)² inside cσ, 0 outside."""
    u = norms / (TUKEY_C * scale)
    return np.where(u < 1.0, (1.0 - u**2) ** 2, 0.0)


def weighted_cost(r: Array, w: Array | None = None) -> float:
    """Mean (weighted) squared residual per feature, px²."""
    sq = r[0::2] ** 2 + r[1::2] ** 2
    if w is None:
        return float(np.mean(sq)) if len(sq) else 0.0
    return _weighted_mean(sq, w)


def capped_cost(r: Array, w: Array, cap_px: float) -> float:
    """weighted_cost with each feature's squared residual capped at ``cap_px``²: a feature that
    jumps (a face turning into or out of the light, an occlusion) counts as an outlier, not by
    the square of its jump. (Found on an Aura view: two of 320 features moved 1.2–1.6 px when
    a trial tilted the sun, 98 % of the cost's rise, and both trials of a pass were rejected.)"""
    return _weighted_mean(np.minimum(r[0::2] ** 2 + r[1::2] ** 2, cap_px**2), w)


def _weighted_mean(sq: Array, w: Array) -> float:
    return float(np.sum(w * sq) / max(np.sum(w), 1e-12))


def irls_increment(
    J: Array, r: Array, iterations: int = 5, w0: Array | None = None, floor: float = MIN_SCALE_PX
) -> tuple[Array, Array, float]:
    """Robust Gauss–Newton increment by IRLS, the Tukey scale at least ``floor`` px; returns
    (δp, weights (k,), scale px)."""
    k = len(r) // 2
    w = np.ones(k) if w0 is None else w0.copy()
    dp = lm_step(J, r, 0.0, w)
    scale = floor
    for _ in range(iterations):
        norms = feature_norms(r - J @ dp)
        scale = robust_scale(norms[w > 0] if (w > 0).any() else norms, floor)
        w = tukey_weights(norms, scale)
        if w.sum() < 3:
            break
        dp = lm_step(J, r, 0.0, w)
    return dp, w, scale


def ransac_increment(
    J: Array,
    r: Array,
    rng: np.random.Generator,
    threshold_px: float,
    iterations: int = 300,
) -> NDArray[np.bool_]:
    """Features consistent with one pose increment: RANSAC over δp on sets of
    RANSAC_SET_SIZE features (an edge point constrains one direction only, so three are not
    always enough for six unknowns), scored by the count within ``threshold_px``. Returns the
    inlier mask (k,), refitted on the best set's inliers."""
    k = len(r) // 2
    if k <= RANSAC_SET_SIZE:
        return np.ones(k, dtype=bool)
    # All sets solved at once (one batched SVD, one matrix product for every residual): the
    # same draws and the same choice as one lstsq per set, some ten times faster.
    picks = np.array([rng.choice(k, RANSAC_SET_SIZE, replace=False) for _ in range(iterations)])
    rows = np.stack([2 * picks, 2 * picks + 1], axis=-1).reshape(iterations, -1)
    U, sv, Vt = np.linalg.svd(J[rows], full_matrices=False)  # (n, 2s, 6), (n, 6), (n, 6, 6)
    solvable = sv[:, -1] >= 1e-9 * sv[:, 0]
    inv = np.divide(1.0, sv, out=np.zeros_like(sv), where=solvable[:, None])
    dps = np.einsum("nji,nj->ni", Vt, np.einsum("nji,nj->ni", U, r[rows]) * inv)  # (n, 6)
    res = r[None, :] - dps @ J.T  # (n, 2k)
    counts = (np.hypot(res[:, 0::2], res[:, 1::2]) < threshold_px).sum(axis=1)
    counts[~solvable] = -1
    best = np.zeros(k, dtype=bool)
    if counts.max() > 0:
        best = feature_norms(r - J @ dps[int(np.argmax(counts))]) < threshold_px
    if best.sum() >= 3:
        dp = lm_step(J, r, 0.0, best.astype(np.float64))
        best = feature_norms(r - J @ dp) < threshold_px
    return best


def covariance(
    J: Array, r: Array, w: Array, x: Array | None = None, cell_px: float = CLUSTER_CELL_PX
) -> tuple[Array, float]:
    """Pose covariance (6, 6) and the residual σ (px) at the optimum.

    Without positions: σ² (JᵀWJ)⁻¹, which takes every feature's error as independent. With the
    features' image positions ``x`` (k, 2): the cluster-robust (sandwich) estimate
    A⁻¹ (Σ_c g_c g_cᵀ) A⁻¹ · G/(G−1), A = JᵀWJ, g_c = Σ_{i∈c} J_iᵀ W_i r_i over the features
    of each ``cell_px`` image cell. Errors shared by nearby features (points along one edge, a
    shading difference over one panel) then count once per cell, not once per feature; of the
    two estimates, the one with the larger trace is returned.
    """
    Wr = expand(w)
    A = (J.T * Wr) @ J
    dof = max(float(np.sum(Wr)) - J.shape[1], 1.0)
    sigma2 = float(np.sum(Wr * r**2)) / dof
    A_inv = np.linalg.pinv(A)
    C = sigma2 * A_inv
    if x is None or len(x) < 2:
        return C, float(np.sqrt(sigma2))
    cells = np.floor(np.asarray(x) / cell_px).astype(np.int64)
    _, cluster = np.unique(cells, axis=0, return_inverse=True)
    G = int(cluster.max()) + 1
    if G < MIN_CLUSTERS:
        return C, float(np.sqrt(sigma2))
    scores = (J * (Wr * r)[:, None]).reshape(len(w), 2, -1).sum(axis=1)  # (k, 6)
    g = np.zeros((G, J.shape[1]))
    np.add.at(g, cluster.ravel(), scores)
    C_cluster = A_inv @ (g.T @ g) @ A_inv * (G / (G - 1.0))
    if np.trace(C_cluster) > np.trace(C):
        C = C_cluster
    return C, float(np.sqrt(sigma2))


def rows_of(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    return np.repeat(mask, 2)


def whiten(A: Array, X: Array) -> Array:
    """Rows (u, v) of each feature, in X (2k,) or (2k, n), multiplied by its A (k, 2, 2)."""
    k = len(A)
    Xk = X.reshape(k, 2, -1)
    return np.einsum("kij,kjn->kin", A, Xk).reshape(X.shape)


@dataclass
class Damping:
    """λ and the counters that end an LM stage: consecutive rejected trials, and accepted steps
    in a row that did not shrink by SLOW_RATIO."""

    lam: float
    rejected: int = 0
    steady: int = 0
    last_step: float = np.inf

    def reject(self) -> None:
        """A rejected trial: a smaller step next time."""
        self.lam *= 10.0
        self.rejected += 1

    def accept(self, step: float) -> None:
        """An accepted trial of size ``step``: a larger step next time."""
        self.rejected = 0
        self.lam = max(self.lam * 0.1, LAMBDA_MIN)
        self.steady = self.steady + 1 if step > SLOW_RATIO * self.last_step else 0
        self.last_step = step
