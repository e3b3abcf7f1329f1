"""The worker reads the limits the API checks uploads against (PROXPOSE_MAX_MODEL_FACES,
PROXPOSE_MAX_IMAGE_PIXELS): raised through the environment, a real worker (RQ's SimpleWorker,
in-process, burst mode) renders and estimates a model above the old default of 2,000,000
faces; lowered, the entry points refuse what the default would take."""

from __future__ import annotations

import hashlib
import json
import secrets
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import redis
from conftest import RedisServer, settings_on_redis
from rq import SimpleWorker
from rq.serializers import JSONSerializer

from schemas import EstimateRequest, RenderRequest
from schemas.models import ModelPublic
from schemas.names import DEFAULT_MAX_MODEL_FACES
from schemas.settings import get_settings
from service.store import JobStore, Keys, ModelStore, Queues
from service.store.blobs import open_blob_store
from worker.engine.exceptions import ImageTooLargeError, ModelTooLargeError
from worker.engine.images import encode_png
from worker.engine.posemath import axis_angle_to_matrix, matrix_to_quaternion

#: Redis database of this module.
DB = 10
#: Vertices of the plane's grid: (GRID_U − 1)(GRID_V − 1)·2 = 2,002,000 triangles.
GRID_U, GRID_V = 1001, 1002
SIDE_PX = 128
CAMERA = {"width": SIDE_PX, "height": SIDE_PX, "fx": 154.0, "fy": 154.0, "cx": 63.5, "cy": 63.5}
#: The plane 3 units in front of the camera, tilted 20° about x.
R_TRUE = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.radians(20.0))
T_TRUE = np.array([0.05, -0.03, 3.0])
#: Light estimate options: straight to one learned-Jacobian pass on KLT corners.
OPTIONS = {"coarse": "none", "max_iterations": 3, "fit_sun": False, "refine_passes": 1}
CUBE_OBJ = (
    "".join(f"v {i & 1} {i >> 1 & 1} {i >> 2 & 1}\n" for i in range(8))
    + "f 1 3 2\nf 2 3 4\nf 5 6 7\nf 6 8 7\nf 1 2 5\nf 2 6 5\n"
    + "f 3 7 4\nf 4 7 8\nf 1 5 3\nf 3 5 7\nf 2 4 6\nf 4 8 6\n"
)


def pose(R: np.ndarray, t: np.ndarray) -> dict[str, list[float]]:
    return {"t": [float(c) for c in t], "quaternion": [float(c) for c in matrix_to_quaternion(R)]}


def checkerboard_plane_ply(path: Path) -> int:
    """A binary PLY of a 2 × 2 plane (z = 0, facing −z) of GRID_U × GRID_V vertices with an
    8 × 8 checkerboard in vertex colours; returns its number of triangles."""
    u, v = np.meshgrid(np.linspace(-1, 1, GRID_U), np.linspace(-1, 1, GRID_V), indexing="xy")
    grey = np.where((np.floor((u + 1) * 4) + np.floor((v + 1) * 4)) % 2 == 0, 40, 220)
    vertices = np.zeros(u.size, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), *(
        (c, "u1") for c in ("red", "green", "blue"))])  # fmt: skip
    vertices["x"], vertices["y"] = u.ravel(), v.ravel()
    for c in ("red", "green", "blue"):
        vertices[c] = grey.ravel()
    i = np.arange(GRID_V - 1)[:, None] * GRID_U + np.arange(GRID_U - 1)[None, :]
    quads = np.stack([i, i + 1, i + GRID_U + 1, i + GRID_U], axis=-1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 2, 1]], quads[:, [0, 3, 2]]])  # wound to face −z
    faces = np.zeros(len(tris), [("n", "u1"), ("v", "<i4", (3,))])
    faces["n"], faces["v"] = 3, tris
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    path.write_bytes(header.encode() + vertices.tobytes() + faces.tobytes())
    return len(faces)


@pytest.fixture
def r(
    redis_server: RedisServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[redis.Redis]:
    env = {"PROXPOSE_MAX_MODEL_FACES": "2100000"}
    with settings_on_redis(redis_server, DB, tmp_path / "data", monkeypatch, env) as client:
        yield client


def _register(r: redis.Redis, keys: Keys, data: bytes, faces: int) -> str:
    sha = hashlib.sha256(data).hexdigest()
    model = ModelPublic(
        id=sha[:16],
        name="checkerboard plane",
        vertices=GRID_U * GRID_V,
        faces=faces,
        bounds=[[-1.0, -1.0, 0.0], [1.0, 1.0, 0.0]],
        textured=False,
        format="ply",
        size_bytes=len(data),
        sha256=sha,
        created_at=datetime.now(UTC),
    )
    ModelStore(r, keys, blobs=open_blob_store(get_settings())).put(model, data)
    return model.id


def _work(r: redis.Redis, queues: Queues) -> None:
    SimpleWorker(queues.all(), connection=r, serializer=JSONSerializer).work(burst=True)


@pytest.mark.slow
def test_a_worker_renders_and_estimates_a_model_above_the_old_face_limit(
    r: redis.Redis, tmp_path: Path, variant: str
) -> None:
    faces = checkerboard_plane_ply(tmp_path / "plane.ply")
    assert DEFAULT_MAX_MODEL_FACES < faces <= get_settings().max_model_faces
    keys = Keys(get_settings().redis_prefix)
    queues = Queues(r, keys)
    model_id = _register(r, keys, (tmp_path / "plane.ply").read_bytes(), faces)

    render = RenderRequest.model_validate({"camera": CAMERA, "pose": pose(R_TRUE, T_TRUE)})
    render_id = secrets.token_hex(8)
    queues.enqueue_render(render_id, model_id, render.model_dump_json(), 300)
    _work(r, queues)
    outcome = json.loads(r.lpop(keys.render_done(render_id)))  # type: ignore[arg-type]
    assert outcome == {"status": "succeeded"}, outcome
    reference = r.get(keys.render_png(render_id))
    assert reference is not None

    R0 = R_TRUE @ axis_angle_to_matrix(np.array([0.3, 1.0, 0.0]), np.radians(0.5))
    request = EstimateRequest.model_validate(
        {"camera": CAMERA, "initial_pose": pose(R0, T_TRUE), "options": OPTIONS}
    )
    store = JobStore(r, keys, retention_s=600, blobs=open_blob_store(get_settings()))
    job_id = secrets.token_hex(16)
    store.create(
        job_id, model_id, request.model_dump_json(), 3, reference, "", owner="t", timeout_s=600
    )
    _work(r, queues)
    record = store.get(job_id)
    assert record is not None and record.status == "succeeded", record and record.error
    assert json.loads(record.result or "{}")["iterations"] >= 1


def test_a_lower_face_limit_refuses_a_render(
    r: redis.Redis, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, variant: str
) -> None:
    from worker.entry import render_png

    monkeypatch.setenv("PROXPOSE_MAX_MODEL_FACES", "11")
    get_settings.cache_clear()
    (tmp_path / "cube.obj").write_text(CUBE_OBJ)  # 12 triangles
    request = RenderRequest.model_validate(
        {"camera": CAMERA, "pose": {"t": [-0.5, -0.5, 4.0], "q": [0.2, 0.3, 0.1]}, "spp": 1}
    )
    with pytest.raises(ModelTooLargeError):
        render_png(tmp_path / "cube.obj", request)


def test_a_lower_pixel_limit_refuses_an_image(
    r: redis.Redis, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, variant: str
) -> None:
    from worker.entry import run_estimate

    monkeypatch.setenv("PROXPOSE_MAX_IMAGE_PIXELS", str(SIDE_PX * SIDE_PX - 1))
    get_settings.cache_clear()
    (tmp_path / "cube.obj").write_text(CUBE_OBJ)
    image = encode_png(np.full((SIDE_PX, SIDE_PX), 0.5, np.float32))
    request = EstimateRequest.model_validate(
        {"camera": CAMERA, "initial_pose": {"t": [-0.5, -0.5, 4.0], "q": [0.2, 0.3, 0.1]}}
    )
    with pytest.raises(ImageTooLargeError):
        run_estimate(tmp_path / "cube.obj", image, request)
