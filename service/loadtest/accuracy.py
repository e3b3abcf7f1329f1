"""The load test's accuracy check: is each converged estimate's pose error within the accuracy
the service stated for it?

The stated accuracy is the result's covariance (``result.covariance``: 1-σ rotation about the
model axes, deg, and 1-σ translation per axis, scene units). The errors the service reports
against the ground truth are magnitudes (the rotation angle ∠ΔR and ‖t − t̂‖), so each is
compared with ``SIGMA_BOUND`` times the root-sum-square of the three 1-σ components (the RMS
magnitude of an error vector with that covariance, its cross-terms left out): an estimate is
within its stated accuracy when ∠ΔR ≤ 3·√(σ²rx + σ²ry + σ²rz) and ‖t − t̂‖ ≤ 3·√(σ²tx + σ²ty +
σ²tz). A converged estimate without a covariance cannot be checked and counts as outside.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any, Protocol

#: How many (root-sum-square) σ a pose error may be.
SIGMA_BOUND = 3.0


def rss(sigmas: Sequence[float] | None) -> float | None:
    """√Σσ² of the per-axis 1-σ figures, or None when there are none."""
    if not sigmas:
        return None
    return math.sqrt(sum(float(s) ** 2 for s in sigmas))


class Checked(Protocol):
    """What the check reads of one estimate (a loadtest JobRun)."""

    status: str | None
    converged: bool | None
    rotation_error_deg: float | None
    translation_error: float | None
    sigma_rotation_deg: float | None
    sigma_translation: float | None


def within_accuracy(job: Checked, bound: float = SIGMA_BOUND) -> bool:
    """True when both pose errors are within ``bound`` × their stated root-sum-square σ."""
    pairs = (
        (job.rotation_error_deg, job.sigma_rotation_deg),
        (job.translation_error, job.sigma_translation),
    )
    return all(
        err is not None and sigma is not None and err <= bound * sigma for err, sigma in pairs
    )


def accuracy_summary(jobs: Iterable[Checked]) -> dict[str, Any]:
    """Of the succeeded estimates: how many converged, how many of those are within their stated
    accuracy (and within 1 σ), and the error in units of the stated σ."""
    succeeded = [j for j in jobs if j.status == "succeeded"]
    converged = [j for j in succeeded if j.converged]
    inside = [j for j in converged if within_accuracy(j)]
    ratios_rot = [
        j.rotation_error_deg / j.sigma_rotation_deg
        for j in converged
        if j.rotation_error_deg is not None and j.sigma_rotation_deg
    ]
    ratios_t = [
        j.translation_error / j.sigma_translation
        for j in converged
        if j.translation_error is not None and j.sigma_translation
    ]
    return {
        "criterion": f"converged and ∠ΔR ≤ {SIGMA_BOUND:g}·√Σσ²_rot and ‖t − t̂‖ ≤ "
        f"{SIGMA_BOUND:g}·√Σσ²_t (the result's covariance)",
        "succeeded": len(succeeded),
        "converged": len(converged),
        "within_stated_accuracy": len(inside),
        "within_1_sigma": sum(within_accuracy(j, 1.0) for j in converged),
        "outside": len(converged) - len(inside),
        "within_pct_of_succeeded": round(100.0 * len(inside) / len(succeeded), 1)
        if succeeded
        else None,
        "rotation_error_in_sigma_max": round(max(ratios_rot), 3) if ratios_rot else None,
        "translation_error_in_sigma_max": round(max(ratios_t), 3) if ratios_t else None,
    }
