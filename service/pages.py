"""What the browser pages need besides HTML: a request framing a model, and cached previews.

The framing is the "sensible default" of the submit form and the view of the model previews: a
pinhole camera with a ``FIELD_OF_VIEW_DEG`` horizontal field of view, the model's bounding
sphere centred on the optical axis and filling ``FILL_FRACTION`` of the shorter image side, seen
obliquely from above with the model's +y up (the glTF convention), the sun behind the camera. A
terrain (a flat bounding box: a DEM patch) is looked down on from a height of a fraction of its
side instead, tilted from the nadir, with the sun above its ground.
Plain-Python math: the API process carries no numpy-heavy code paths of its own.
"""

from __future__ import annotations

import math
from typing import Any

import redis

from schemas.jobs import EstimateCreate, RenderCreate
from schemas.lighting import Lighting
from schemas.models import ModelPublic
from service.quaternions import Quaternion, Vector3, axis_quaternion, multiply, rotate
from service.store import Keys

#: Horizontal field of view of the suggested camera, degrees.
FIELD_OF_VIEW_DEG = 45.0
#: Image diameter of the bounding sphere as a fraction of the shorter image side.
FILL_FRACTION = 0.8
#: Attitude of the suggested view, as rotations applied in turn to the model frame:
#: yaw about the model's y axis, a half turn about x (model +y up, +z towards the camera), then
#: a tilt about the camera's x axis so that the camera looks slightly down on the model.
VIEW_YAW_DEG = 35.0
VIEW_TILT_DEG = -20.0
#: A model whose extent along its thinnest axis is below TERRAIN_FLATNESS × the smaller of the
#: other two is a terrain (a DEM patch): it is seen from above, not framed whole.
TERRAIN_FLATNESS = 0.25
#: The terrain view: camera height above the patch centre as a fraction of the patch's smaller
#: side, tilt from the nadir (deg), and the sun's elevation above the ground and azimuth (deg).
TERRAIN_ALTITUDE_FRACTION = 0.3
TERRAIN_TILT_DEG = 25.0
TERRAIN_SUN_ELEVATION_DEG = 35.0
TERRAIN_SUN_AZIMUTH_DEG = 120.0
#: Per thin ("up") axis of a terrain: the rotation taking it to the camera's −z (looking down).
_LOOK_DOWN = {0: ((0.0, 1.0, 0.0), 90.0), 1: ((1.0, 0.0, 0.0), -90.0), 2: ((1.0, 0.0, 0.0), 180.0)}
#: Side of a model preview, px, and its samples per pixel.
PREVIEW_SIDE_PX = 256
PREVIEW_SPP = 16
#: Bump when the preview's framing or look changes, so cached previews are not reused.
PREVIEW_VERSION = 1
#: How long a rendered preview stays in Redis, s (it is re-rendered on demand afterwards).
PREVIEW_TTL_S = 30 * 24 * 3600


def view_quaternion() -> Quaternion:
    """Attitude (model to camera) of the suggested oblique view, [w, x, y, z] with w ≥ 0."""
    yaw = axis_quaternion((0.0, 1.0, 0.0), VIEW_YAW_DEG)
    flip = axis_quaternion((1.0, 0.0, 0.0), 180.0)
    tilt = axis_quaternion((1.0, 0.0, 0.0), VIEW_TILT_DEG)
    q = multiply(tilt, multiply(flip, yaw))
    return q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])


def bounding_sphere(bounds: list[list[float]]) -> tuple[Vector3, float]:
    """Centre (model frame) and radius of the sphere through the box's corners."""
    lo, hi = bounds
    centre = ((lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0)
    return centre, math.dist(lo, hi) / 2.0


def suggested_camera(width: int, height: int) -> dict[str, float]:
    """Square-pixel camera of ``FIELD_OF_VIEW_DEG`` across ``width``, principal point centred."""
    f = (width / 2.0) / math.tan(math.radians(FIELD_OF_VIEW_DEG) / 2.0)
    return {
        "width": width,
        "height": height,
        "fx": round(f, 3),
        "fy": round(f, 3),
        "cx": (width - 1) / 2.0,
        "cy": (height - 1) / 2.0,
    }


def suggested_pose(bounds: list[list[float]], camera: dict[str, float]) -> dict[str, list[float]]:
    """A pose putting the bounding sphere on the optical axis, filling ``FILL_FRACTION``.

    A sphere of radius r at distance d on the axis images as a disc of radius
    f·r/√(d² − r²) px; setting that to ``FILL_FRACTION``·min(w, h)/2 gives
    d = r·√(1 + (f/ρ)²) with ρ the wanted radius in px. Then t = [0, 0, d] − R c.
    """
    centre, radius = bounding_sphere(bounds)
    radius = max(radius, 1e-6)
    rho_px = FILL_FRACTION * min(camera["width"], camera["height"]) / 2.0
    f = min(camera["fx"], camera["fy"])
    d = radius * math.sqrt(1.0 + (f / rho_px) ** 2)
    q = view_quaternion()
    Rc = rotate(q, centre)
    t = [-Rc[0], -Rc[1], d - Rc[2]]
    return {"t": [round(c, 6) for c in t], "quaternion": [round(c, 7) for c in q]}


def terrain_up_axis(bounds: list[list[float]]) -> int | None:
    """The thin axis of a terrain-like (flat) bounding box, or None for any other model."""
    extent = [hi - lo for lo, hi in zip(bounds[0], bounds[1], strict=True)]
    up = min(range(3), key=lambda k: extent[k])
    others = [extent[k] for k in range(3) if k != up]
    return up if extent[up] < TERRAIN_FLATNESS * min(others) else None


def terrain_view(bounds: list[list[float]], up: int) -> tuple[dict[str, list[float]], Vector3]:
    """Pose and sun (camera frame) looking down at a terrain's centre from
    TERRAIN_ALTITUDE_FRACTION of its smaller side, tilted TERRAIN_TILT_DEG from the nadir.

    The attitude turns the up axis to the camera's −z, then tilts about the camera's x axis;
    the patch centre is put on the optical axis at the slant range h / cos(tilt).
    """
    axis, angle = _LOOK_DOWN[up]
    q = multiply(axis_quaternion((1.0, 0.0, 0.0), TERRAIN_TILT_DEG), axis_quaternion(axis, angle))
    q = q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])
    centre, _ = bounding_sphere(bounds)
    side = min(hi - lo for k, (lo, hi) in enumerate(zip(*bounds, strict=True)) if k != up)
    d = TERRAIN_ALTITUDE_FRACTION * side / math.cos(math.radians(TERRAIN_TILT_DEG))
    Rc = rotate(q, centre)
    t = [-Rc[0], -Rc[1], d - Rc[2]]
    e, a = math.radians(TERRAIN_SUN_ELEVATION_DEG), math.radians(TERRAIN_SUN_AZIMUTH_DEG)
    h1, h2 = [k for k in range(3) if k != up]
    sun = [0.0, 0.0, 0.0]
    sun[up], sun[h1], sun[h2] = math.sin(e), math.cos(e) * math.cos(a), math.cos(e) * math.sin(a)
    pose = {"t": [round(c, 6) for c in t], "quaternion": [round(c, 7) for c in q]}
    return pose, rotate(q, (sun[0], sun[1], sun[2]))


def suggested_request(model: ModelPublic, width: int, height: int) -> dict[str, Any]:
    """The submit form's defaults for ``model``: an EstimateCreate document (validated). A
    terrain (a flat bounding box) is looked down on obliquely, lit by a sun above its ground."""
    camera = suggested_camera(width, height)
    lighting = Lighting()
    pose, sun = suggested_pose(model.bounds, camera), lighting.sun_direction
    up = terrain_up_axis(model.bounds)
    if up is not None:
        pose, sun_camera = terrain_view(model.bounds, up)
        norm = math.sqrt(sum(c * c for c in sun_camera))
        sun = [round(c / norm, 7) for c in sun_camera]
    request = {
        "model_id": model.id,
        "camera": camera,
        "initial_pose": pose,
        "lighting": {
            "sun_direction": sun,
            "sun_irradiance": lighting.sun_irradiance,
            "ambient": lighting.ambient,
        },
        "options": {"method": "default"},
    }
    EstimateCreate.model_validate(request)  # the defaults must always be a valid request
    return request


def preview_render(model: ModelPublic) -> RenderCreate:
    """The render request of ``model``'s preview."""
    request = suggested_request(model, PREVIEW_SIDE_PX, PREVIEW_SIDE_PX)
    return RenderCreate.model_validate(
        {
            "model_id": model.id,
            "camera": request["camera"],
            "pose": request["initial_pose"],
            "lighting": request["lighting"],
            "spp": PREVIEW_SPP,
        }
    )


def preview_tag(model: ModelPublic) -> str:
    """Identifies a preview's content: the model file and the preview version (an ETag)."""
    return f"{model.sha256[:16]}-v{PREVIEW_VERSION}"


class PreviewCache:
    """Rendered previews in Redis, keyed by the model file's hash (so never stale).

    Key ``<prefix>:preview:<tag>`` (a string holding the PNG), beside the keys of
    ``service.store.keys.Keys``; it expires after ``PREVIEW_TTL_S``.
    """

    def __init__(self, r: redis.Redis, keys: Keys) -> None:
        self.r = r
        self.keys = keys

    def key(self, model: ModelPublic) -> str:
        return f"{self.keys.prefix}:preview:{preview_tag(model)}"

    def get(self, model: ModelPublic) -> bytes | None:
        return self.r.get(self.key(model))  # type: ignore[return-value]

    def put(self, model: ModelPublic, png: bytes) -> None:
        self.r.set(self.key(model), png, ex=PREVIEW_TTL_S)
