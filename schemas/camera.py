"""Pinhole camera intrinsics in OpenCV conventions."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

#: Image sides accepted, in pixels.
IMAGE_SIDE_MIN_PX = 16
IMAGE_SIDE_MAX_PX = 4096

PositiveFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class Camera(BaseModel):
    """Intrinsics K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] and the image size.

    Pixel coordinates are OpenCV's: the centre of the top-left pixel is (0, 0), u grows right,
    v grows down. A non-square pixel (fx ≠ fy) and a skew are rendered exactly.
    """

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"width": 512, "height": 512, "fx": 955.5, "fy": 955.5, "cx": 255.5, "cy": 255.5}
            ]
        },
    )

    width: int = Field(ge=IMAGE_SIDE_MIN_PX, le=IMAGE_SIDE_MAX_PX, description="Image width, px.")
    height: int = Field(ge=IMAGE_SIDE_MIN_PX, le=IMAGE_SIDE_MAX_PX, description="Image height, px.")
    fx: PositiveFloat = Field(description="Focal length along u, px.")
    fy: PositiveFloat = Field(description="Focal length along v, px.")
    cx: FiniteFloat = Field(description="Principal point u, px (OpenCV: top-left pixel centre 0).")
    cy: FiniteFloat = Field(description="Principal point v, px.")
    skew: FiniteFloat = Field(default=0.0, description="Skew γ, px (K[0][1]).")

    @model_validator(mode="after")
    def _plausible(self) -> Camera:
        for name, c, side in (("cx", self.cx, self.width), ("cy", self.cy, self.height)):
            if not -side <= c <= 2 * side:
                raise ValueError(f"{name} = {c} is implausibly far outside the image (0..{side})")
        for name, f, side in (("fx", self.fx, self.width), ("fy", self.fy, self.height)):
            if not 0.05 * side <= f <= 1000.0 * side:
                raise ValueError(
                    f"{name} = {f} px gives a field of view outside 0.06°..170° "
                    f"for a {side} px side"
                )
        if abs(self.fx / self.fy - 1.0) > 0.5:
            raise ValueError("fx / fy must be within 0.5..1.5 (pixel aspect ratio)")
        if abs(self.skew) > 0.2 * self.fx:
            raise ValueError("|skew| must be at most 0.2·fx")
        return self

    @property
    def K(self) -> list[list[float]]:
        """The 3×3 intrinsic matrix, rows."""
        return [[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
