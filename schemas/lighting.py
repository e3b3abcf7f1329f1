"""Illumination of the scene: a directional sun plus uniform ambient light."""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]

#: How far from unit norm sun_direction may be.
SUN_DIRECTION_NORM_TOLERANCE = 1e-3


class Lighting(BaseModel):
    """A sun (directional light) and an ambient term, both in the camera frame."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"sun_direction": [0.0, -0.6, -0.8], "sun_irradiance": 3.0, "ambient": 0.02}
            ]
        },
    )

    sun_direction: Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)] = Field(
        default=[0.0, -0.6, -0.8],
        description="Unit vector from the target towards the sun, camera frame (x right, y down, "
        "z forward). The default lights the target from above and behind the camera.",
    )
    sun_irradiance: float = Field(
        default=3.0,
        gt=0.0,
        le=1e6,
        allow_inf_nan=False,
        description="Sun irradiance on a surface facing it, in the renderer's linear radiance "
        "units (a white diffuse surface facing the sun renders at irradiance/π).",
    )
    ambient: float = Field(
        default=0.02,
        ge=0.0,
        le=1e6,
        allow_inf_nan=False,
        description="Radiance of a uniform environment (earthshine, scattered light); hidden "
        "from the camera, so the background stays black.",
    )

    @field_validator("sun_direction")
    @classmethod
    def _unit(cls, v: list[float]) -> list[float]:
        norm = math.sqrt(sum(c * c for c in v))
        if abs(norm - 1.0) > SUN_DIRECTION_NORM_TOLERANCE:
            raise ValueError(f"must be a unit vector (got norm {norm:.6g})")
        return [c / norm for c in v]
