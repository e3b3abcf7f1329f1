"""A loaded mesh part as a Mitsuba mesh: its reflectance (texture prefiltered to the working
range, vertex colours or an albedo), two-sided, with the file's or faceted shading normals."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from worker.engine.meshes import MeshPart

#: Texture resolution kept at the working range, texels per pixel. A camera integrates the
#: surface's full detail over each pixel; a texture prefiltered much below that makes every
#: textured feature softer (and elsewhere) in our render than in the image, while one far
#: finer aliases into sampling noise. Measured on references with unfiltered textures: 6
#: texels per pixel left half the start-at-truth drift of 1.5 on the textured models.
TEXELS_PER_PIXEL = 6.0


def prefiltered_texture(part: MeshPart, px_per_unit: float | None) -> NDArray[np.float32]:
    """The part's texture downsampled to about TEXELS_PER_PIXEL at ``px_per_unit``."""
    assert part.texture is not None
    if not px_per_unit:
        return part.texture
    factor = part.texels_per_unit / (TEXELS_PER_PIXEL * px_per_unit)
    if factor <= 1.0:
        return part.texture
    import cv2

    h, w = part.texture.shape[:2]
    size = (max(8, round(w / factor)), max(8, round(h / factor)))
    return cv2.resize(part.texture, size, interpolation=cv2.INTER_AREA)


def scene_mesh(
    part: MeshPart, name: str, px_per_unit: float | None = None, shading: str = "file"
) -> object:
    """A Mitsuba mesh with a two-sided diffuse BSDF (texture, vertex colours or an albedo)."""
    import mitsuba as mi

    if part.texture is not None:
        reflectance: object = {
            "type": "bitmap",
            "bitmap": mi.Bitmap(prefiltered_texture(part, px_per_unit)),
            "raw": True,
            "filter_type": "bilinear",
        }
    elif part.vertex_colors is not None:
        reflectance = {"type": "mesh_attribute", "name": "vertex_color"}
    else:
        reflectance = {"type": "rgb", "value": list(part.albedo)}
    props = mi.Properties()
    # Two-sided: a face wound the other way (normals into the ground), an inconsistently wound
    # mesh or an open surface seen from behind reflects like its front instead of rendering black.
    diffuse = {"type": "diffuse", "reflectance": reflectance}
    props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": diffuse})
    has_normals = part.normals is not None and shading == "file"
    has_uv = part.uvs is not None and part.texture is not None
    mesh = mi.Mesh(
        name,
        len(part.vertices),
        len(part.faces),
        props=props,
        has_vertex_normals=has_normals,
        has_vertex_texcoords=has_uv,
    )
    params = mi.traverse(mesh)

    def put(key: str, values: NDArray[np.generic]) -> None:
        params[key] = type(params[key])(np.ascontiguousarray(values).ravel())

    put("vertex_positions", part.vertices)
    put("faces", part.faces)
    if has_normals:
        put("vertex_normals", part.normals)  # type: ignore[arg-type]
    if has_uv:
        put("vertex_texcoords", part.uvs)  # type: ignore[arg-type]
    if part.vertex_colors is not None:
        mesh.add_attribute("vertex_color", 3, part.vertex_colors.ravel().tolist())
    params.update()
    return mesh
