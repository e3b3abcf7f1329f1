"""Target models as the service stores and lists them (``/v1/models``)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import BaseModel, Field

#: Model ids: the built-in "demo-sat", or the first 16 hex digits of the file's SHA-256.
MODEL_ID_PATTERN = r"^[a-z0-9][a-z0-9-]{0,63}$"
#: Hex digits of the SHA-256 that make an uploaded model's id.
MODEL_ID_HEX_DIGITS = 16
#: Longest model name, characters.
MODEL_NAME_MAX_CHARS = 200

Corner = Annotated[list[float], Field(min_length=3, max_length=3)]


class ModelPublic(BaseModel):
    """A registered model: what a client needs to pick it and place a camera around it."""

    id: str = Field(description="Content address (SHA-256 prefix), or 'demo-sat'.")
    name: str
    vertices: int = Field(description="Vertices over all mesh instances.")
    faces: int = Field(description="Triangles over all mesh instances.")
    bounds: Annotated[list[Corner], Field(min_length=2, max_length=2)] = Field(
        description="Axis-aligned bounding box [[xmin, ymin, zmin], [xmax, ymax, zmax]] in the "
        "file's own units and frame (poses are expressed in them)."
    )
    textured: bool = Field(description="Whether some part carries a base-colour texture.")
    format: str = Field(description="File format: obj, ply, stl, glb or gltf.")
    size_bytes: int = Field(description="Size of the model file, bytes.")
    sha256: str = Field(description="SHA-256 of the model file, hex.")
    created_at: datetime
    builtin: bool = Field(default=False, description="True for the demo satellite.")


class ModelList(BaseModel):
    """All registered models, newest first."""

    items: list[ModelPublic]
