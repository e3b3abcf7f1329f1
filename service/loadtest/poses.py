"""The load test's initial guesses: each estimate starts from its own small perturbation of
the true pose (deterministic in the estimate's index)."""

from __future__ import annotations

import math
import random
from typing import Any

from service.quaternions import axis_quaternion, multiply

#: Initial guesses: rotated this far about a random axis (the default of ``perturbed_pose``;
#: a run states its own, ``--start-deg``), moved this fraction of the range.
PERTURB_ROT_DEG = 2.0
PERTURB_TRANS_FRAC = 0.01


def _unit(v: list[float]) -> list[float]:
    norm = math.sqrt(sum(x * x for x in v))
    return [x / norm for x in v]


def perturbed_pose(
    truth: dict[str, Any], seed: int, rotation_deg: float = PERTURB_ROT_DEG
) -> dict[str, list[float]]:
    """``truth`` rotated by ``rotation_deg`` about a random axis (camera frame) and moved by
    ``PERTURB_TRANS_FRAC`` of its range in a random direction (deterministic in ``seed``)."""
    rng = random.Random(seed)
    axis = _unit([rng.gauss(0.0, 1.0) for _ in range(3)])
    delta = axis_quaternion((axis[0], axis[1], axis[2]), rotation_deg)
    q = multiply(delta, tuple(truth["quaternion"]))  # type: ignore[arg-type]
    norm = math.sqrt(sum(x * x for x in q))
    t = [float(x) for x in truth["t"]]
    shift = PERTURB_TRANS_FRAC * math.sqrt(sum(x * x for x in t))
    step = _unit([rng.gauss(0.0, 1.0) for _ in range(3)])
    return {
        "t": [round(x + shift * d, 6) for x, d in zip(t, step, strict=True)],
        "quaternion": [round(x / norm, 9) for x in q],
    }
