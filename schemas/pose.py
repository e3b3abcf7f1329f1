"""Pose of the target: model frame to camera frame, b = R a + t.

The attitude may be given in exactly one of three forms. They are checked here in plain Python
(the contract carries no numpy), and converted to matrices by ``worker.engine.posemath``.
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Vector3 = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
Quaternion = Annotated[list[FiniteFloat], Field(min_length=4, max_length=4)]
Matrix3 = Annotated[list[Vector3], Field(min_length=3, max_length=3)]

#: How far from unit norm a given quaternion may be (it is then normalised).
QUATERNION_NORM_TOLERANCE = 1e-3
#: Largest |RᵀR − I| element accepted for a given rotation matrix (it is then re-orthonormalised).
ROTATION_ORTHONORMALITY_TOLERANCE = 1e-3
#: Largest Gibbs vector norm accepted: tan(θ/2) grows without bound as θ → 180°.
GIBBS_NORM_MAX = 1e6


def _det3(M: list[list[float]]) -> float:
    return (
        M[0][0] * (M[1][1] * M[2][2] - M[1][2] * M[2][1])
        - M[0][1] * (M[1][0] * M[2][2] - M[1][2] * M[2][0])
        + M[0][2] * (M[1][0] * M[2][1] - M[1][1] * M[2][0])
    )


def _orthonormality_error(M: list[list[float]]) -> float:
    worst = 0.0
    for i in range(3):
        for j in range(3):
            dot = sum(M[k][i] * M[k][j] for k in range(3))
            worst = max(worst, abs(dot - (1.0 if i == j else 0.0)))
    return worst


class Pose(BaseModel):
    """A 6-DoF pose given by the client: ``t`` plus exactly one of ``q``, ``quaternion`` or ``R``.

    The pose maps a point ``a`` in the model file's own frame to the camera frame,
    ``b = R a + t``. The camera frame is OpenCV's: x right, y down, z forward.
    """

    model_config = ConfigDict(extra="forbid")

    t: Vector3 = Field(
        description="Translation [x, y, z] in scene units (the model file's units): the model "
        "origin in the camera frame. z must be positive (in front of the camera).",
        examples=[[0.0, 0.0, 60.0]],
    )
    q: Vector3 | None = Field(
        default=None,
        description="Gibbs vector (classical Rodrigues parameters) of R under the paper's Cayley "
        "transform R = (I + [q×])⁻¹(I − [q×]); q = −tan(θ/2)·axis for an active rotation by θ. "
        "Singular at 180°.",
    )
    quaternion: Quaternion | None = Field(
        default=None,
        description="Unit quaternion [w, x, y, z] (scalar first, Hamilton) of the active rotation "
        "R. Normalised if within 1e-3 of unit norm.",
    )
    R: Matrix3 | None = Field(
        default=None,
        description="Rotation matrix, 3 rows of 3. Must be orthonormal within 1e-3 with det +1.",
    )

    @model_validator(mode="after")
    def _one_attitude(self) -> Pose:
        given = [name for name in ("q", "quaternion", "R") if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError(
                "give exactly one of 'q', 'quaternion' or 'R' for the attitude"
                + (f" (got {', '.join(given)})" if given else " (got none)")
            )
        if self.t[2] <= 0.0:
            raise ValueError("t[2] must be > 0: the target must be in front of the camera")
        if self.quaternion is not None:
            norm = math.sqrt(sum(c * c for c in self.quaternion))
            if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
                raise ValueError(f"quaternion must have unit norm (got norm {norm:.6g})")
            self.quaternion = [c / norm for c in self.quaternion]
        if self.q is not None and math.sqrt(sum(c * c for c in self.q)) > GIBBS_NORM_MAX:
            raise ValueError(
                "q is too large (attitude too close to 180°); give 'quaternion' or 'R'"
            )
        if self.R is not None:
            err = _orthonormality_error(self.R)
            if err > ROTATION_ORTHONORMALITY_TOLERANCE:
                raise ValueError(f"R must be orthonormal (largest |RᵀR − I| entry {err:.3g})")
            if _det3(self.R) <= 0.0:
                raise ValueError("R must be a proper rotation (det R = +1, got a reflection)")
        return self


class PoseOut(BaseModel):
    """A pose reported in every form: R, Gibbs vector q, quaternion [w, x, y, z], and t."""

    R: Matrix3 = Field(description="Rotation matrix, model to camera, 3 rows of 3.")
    q: Vector3 = Field(description="Gibbs vector under the paper's Cayley transform.")
    quaternion: Quaternion = Field(description="Unit quaternion [w, x, y, z], w ≥ 0.")
    t: Vector3 = Field(description="Translation in scene units, camera frame.")
