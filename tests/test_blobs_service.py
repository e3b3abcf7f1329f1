"""The service's bytes in the blob store, on each backend (a directory; an S3-compatible server
process), through the API on a real Redis: Redis keeps only metadata, artifacts are served from
the store with ETags, a store that is down is a clean 503 with nothing enqueued, the sweep
retires what no record names, and an older deployment's bytes in Redis are still served and
are moved by ``proxpose migrate-blobs``."""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import redis
from blob_helpers import backend as backend  # noqa: F401 (fixture)
from blob_helpers import backend_env
from blob_helpers import s3_server as s3_server  # noqa: F401 (fixture)
from conftest import REPO, free_port, settings_on_redis
from fastapi.testclient import TestClient
from service_api_helpers import KEYS, png, queued, submit

from schemas.settings import get_settings
from service.main import create_app
from service.store import JobStore, Leases
from service.store.blobs import BlobStore, job_image_name, open_blob_store
from service.store.blobs.sweeper import BlobSweeper

#: Redis database of this module.
DB = 12
#: Redis memory one queued or finished job may take here (hash, index entries, RQ job), bytes.
#: A real estimate's result JSON adds a few kB: test_blobs_e2e measures that.
JOB_REDIS_BUDGET_BYTES = 6_000
ARTIFACTS = {"difference": png(64, 64), "overlay_final": png(32, 32)}


@dataclass
class Svc:
    client: TestClient
    r: redis.Redis
    blobs: BlobStore
    env: dict[str, str]


def _service(
    backend: str, redis_server, tmp_path: Path, monkeypatch, request, broken: bool = False
) -> Iterator[Svc]:  # type: ignore[no-untyped-def]
    s3 = request.getfixturevalue("s3_server") if backend == "s3" else None
    env = backend_env(backend, tmp_path, s3)
    if broken and backend == "file":
        env["PROXPOSE_BLOB_STORE"] = "file:///dev/null/blobs"  # can never be a directory
    elif broken:
        env["PROXPOSE_S3_ENDPOINT_URL"] = f"http://127.0.0.1:{free_port()}"  # nobody there
        env["PROXPOSE_BLOB_TIMEOUT_S"] = "1"
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch, env) as r:
        with TestClient(create_app()) as client:
            yield Svc(client, r, open_blob_store(get_settings()), env)


@pytest.fixture(name="svc")
def working_service(backend, redis_server, tmp_path, monkeypatch, request) -> Iterator[Svc]:  # type: ignore[no-untyped-def]  # noqa: F811
    yield from _service(backend, redis_server, tmp_path, monkeypatch, request)


@pytest.fixture(name="down")
def service_with_store_down(backend, redis_server, tmp_path, monkeypatch, request) -> Iterator[Svc]:  # type: ignore[no-untyped-def]  # noqa: F811
    yield from _service(backend, redis_server, tmp_path, monkeypatch, request, broken=True)


def _job_memory(r: redis.Redis, job_id: str) -> int:
    """Redis memory of every key naming the job (its hash, RQ's job hash), bytes."""
    return sum(int(r.memory_usage(k) or 0) for k in r.scan_iter(match=f"*{job_id}*"))


def _finish_like_a_worker(svc: Svc, job_id: str, attempt: int = 1) -> JobStore:
    store = JobStore(svc.r, KEYS, 600, blobs=svc.blobs)
    record = store.get(job_id)
    assert record is not None
    assert Leases(store, 30.0).start(job_id, "test-worker", record.rq_id) is not None
    assert store.finish(job_id, "succeeded", attempt=attempt, artifacts=ARTIFACTS)
    return store


# ----------------------------------------------------------------------------- submit, serve
def test_the_image_goes_to_the_store_and_redis_keeps_a_few_hundred_bytes(svc: Svc) -> None:
    image = png()
    response = submit(svc.client, image=image)
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    assert svc.blobs.get(job_image_name(job_id)) == image
    assert not svc.r.exists(KEYS.job_image(job_id))
    assert svc.r.hget(KEYS.job(job_id), "image_blob") == job_image_name(job_id).encode()
    assert 0 < _job_memory(svc.r, job_id) < JOB_REDIS_BUDGET_BYTES
    record = JobStore(svc.r, KEYS, 600, blobs=svc.blobs).get(job_id)
    assert record is not None
    assert JobStore(svc.r, KEYS, 600, blobs=svc.blobs).get_image(record) == image


def test_artifacts_are_served_from_the_store_with_an_etag(svc: Svc) -> None:
    job_id = submit(svc.client).json()["id"]
    _finish_like_a_worker(svc, job_id)
    assert svc.blobs.get(job_image_name(job_id)) is None  # an ended job's image goes
    assert not any(svc.r.exists(KEYS.job_artifact(job_id, n)) for n in ARTIFACTS)
    assert _job_memory(svc.r, job_id) < JOB_REDIS_BUDGET_BYTES
    job = svc.client.get(f"/v1/estimates/{job_id}").json()
    assert set(job["artifacts"]) == set(ARTIFACTS)
    for name, data in ARTIFACTS.items():
        got = svc.client.get(job["artifacts"][name])
        assert got.status_code == 200 and got.content == data
        assert got.headers["content-type"] == "image/png"
        assert got.headers["etag"] == f'"{hashlib.sha256(data).hexdigest()}"'
        assert "immutable" in got.headers["cache-control"]
        again = svc.client.get(
            job["artifacts"][name], headers={"If-None-Match": got.headers["etag"]}
        )
        assert again.status_code == 304 and again.content == b""
        assert again.headers["etag"] == got.headers["etag"]
        other = svc.client.get(job["artifacts"][name], headers={"If-None-Match": '"other"'})
        assert other.status_code == 200
    missing = svc.client.get(f"/v1/estimates/{job_id}/artifacts/nope.png")
    assert missing.status_code == 404 and "difference" in missing.json()["detail"]


def test_a_retired_artifact_is_404(svc: Svc) -> None:
    job_id = submit(svc.client).json()["id"]
    _finish_like_a_worker(svc, job_id)
    svc.blobs.delete([e.name for e in svc.blobs.list(f"jobs/{job_id}/")])
    assert svc.client.get(f"/v1/estimates/{job_id}/artifacts/difference").status_code == 404
    svc.r.delete(KEYS.job(job_id))  # the job expired
    assert svc.client.get(f"/v1/estimates/{job_id}/artifacts/difference").status_code == 404


def test_a_superseded_attempt_leaves_no_artifacts(svc: Svc) -> None:
    job_id = submit(svc.client).json()["id"]
    store = JobStore(svc.r, KEYS, 600, blobs=svc.blobs)
    record = store.get(job_id)
    assert record is not None and Leases(store, 30.0).start(job_id, "w", record.rq_id)
    assert not store.finish(job_id, "succeeded", attempt=7, artifacts=ARTIFACTS)  # fenced off
    assert [e.name for e in svc.blobs.list(f"jobs/{job_id}/")] == [job_image_name(job_id)]


def test_a_model_file_lives_in_the_store_until_its_last_owner_lets_go(svc: Svc) -> None:
    from e2e_helpers import CUBE_OBJ

    model = svc.client.post("/v1/models", files={"file": ("cube.obj", CUBE_OBJ)}).json()
    names = [e.name for e in svc.blobs.list("models/")]
    assert names == [f"models/{model['id']}/{model['sha256']}"]
    assert not svc.r.exists(KEYS.model_data(model["id"]))
    assert svc.client.delete(f"/v1/models/{model['id']}").status_code == 204
    assert list(svc.blobs.list("models/")) == []


# ----------------------------------------------------------------------------- store down
def test_a_store_that_is_down_is_a_503_naming_it_and_nothing_is_enqueued(down: Svc) -> None:
    from e2e_helpers import CUBE_OBJ

    response = submit(down.client, headers={"Idempotency-Key": "k-1"})
    assert response.status_code == 503, response.text
    assert response.json()["detail"].startswith("the blob store (")
    assert "unavailable" in response.json()["detail"] and "Traceback" not in response.text
    assert response.headers["retry-after"]
    assert queued(down.r) == 0
    left = {k.decode() for k in down.r.scan_iter()}
    assert left <= {KEYS.jobs_seq, KEYS.rate("anonymous")}, left  # no record, place or claim
    model = down.client.post("/v1/models", files={"file": ("cube.obj", CUBE_OBJ)})
    assert model.status_code == 503 and "blob store" in model.json()["detail"]
    assert down.r.zcard(KEYS.models_index) == 0
    ready = down.client.get("/readyz")
    assert ready.status_code == 503
    assert ready.json()["blob_store"] is False and ready.json()["redis"] is True
    assert "blob store" in ready.json()["reason"]


def test_readyz_reports_a_working_store(svc: Svc) -> None:
    body = svc.client.get("/readyz").json()
    assert body["blob_store"] is True and body["redis"] is True
    assert "blob store" not in (body["reason"] or "")  # only the missing worker


# ----------------------------------------------------------------------------- sweep, metrics
def test_the_sweep_retires_what_no_record_names_and_keeps_the_rest(svc: Svc) -> None:
    kept = submit(svc.client).json()["id"]
    _finish_like_a_worker(svc, kept)
    expired = submit(svc.client).json()["id"]
    _finish_like_a_worker(svc, expired)
    svc.r.delete(KEYS.job(expired))  # its retention ran out
    queued_id = submit(svc.client).json()["id"]
    svc.blobs.put(f"jobs/{kept}/a9/difference.png", b"a superseded attempt's")
    orphan = secrets.token_hex(16)
    svc.blobs.put(job_image_name(orphan), b"written just before its record")
    svc.blobs.put("models/0123456789abcdef/" + "0" * 64, b"a model deleted meanwhile")

    first = BlobSweeper(svc.r, KEYS, svc.blobs).sweep()  # within the grace: young orphans stay
    names = {e.name for e in svc.blobs.list("")}
    assert f"jobs/{kept}/a9/difference.png" not in names  # an ended job does not name it
    assert job_image_name(orphan) in names and job_image_name(queued_id) in names
    assert any(n.startswith(f"jobs/{expired}/") for n in names)
    assert first.deleted == 1

    BlobSweeper(svc.r, KEYS, svc.blobs, grace_s=0.0).sweep()
    names = {e.name for e in svc.blobs.list("")}
    expected = {
        json.loads(svc.r.hget(KEYS.job(kept), "artifact_blobs"))[n]["blob"] for n in ARTIFACTS
    }  # type: ignore[arg-type]
    assert names == expected | {job_image_name(queued_id)}
    census = {k.decode(): float(v) for k, v in svc.r.hgetall(KEYS.blob_census).items()}
    assert census["objects"] == len(names)
    assert census["bytes"] == sum(len(d) for d in ARTIFACTS.values()) + len(png())
    metrics = svc.client.get("/metrics").text
    assert f"proxpose_blob_store_objects {float(len(names))}" in metrics
    assert "proxpose_redis_used_memory_bytes" in metrics
    assert "proxpose_redis_maxmemory_bytes 0.0" in metrics
    assert 'proxpose_blob_operations_total{op="put",outcome="ok"}' in metrics
    assert 'proxpose_blob_transferred_bytes_total{direction="write"}' in metrics


def test_the_sweep_runs_once_per_period_across_workers(svc: Svc) -> None:
    a = BlobSweeper(svc.r, KEYS, svc.blobs)
    b = BlobSweeper(svc.r, KEYS, svc.blobs)
    assert a.sweep_if_due(60) is not None
    assert b.sweep_if_due(60) is None


# ----------------------------------------------------------------------------- older deployments
#: A result as an older deployment stored it: plain JSON in the hash's ``result`` field.
LEGACY_RESULT = json.dumps({"iterations": 3, "history": [{"iteration": i} for i in (1, 2, 3)]})


def _legacy_records(r: redis.Redis) -> tuple[str, str, str, bytes]:
    """What an API and worker before the blob store left in Redis: a finished job with its
    artifact, a queued job with its image, a model with its file; (ids..., model bytes)."""
    from datetime import UTC, datetime

    from e2e_helpers import CUBE_OBJ

    from schemas.models import ModelPublic

    done, waiting = secrets.token_hex(16), secrets.token_hex(16)
    base = {"model_id": "demo-sat", "created_at": "2026-01-01T00:00:00+00:00", "request": "{}"}
    r.hset(KEYS.job(done), mapping={"id": done, "status": "succeeded", "seq": 1, **base})
    r.hset(KEYS.job(done), mapping={"max_iterations": 3, "artifacts": '["difference"]'})
    r.hset(KEYS.job(done), "result", LEGACY_RESULT)
    r.set(KEYS.job_artifact(done, "difference"), ARTIFACTS["difference"])
    r.hset(KEYS.job(waiting), mapping={"id": waiting, "status": "queued", "seq": 2, **base})
    r.hset(KEYS.job(waiting), "max_iterations", 3)
    r.set(KEYS.job_image(waiting), png())
    sha = hashlib.sha256(CUBE_OBJ).hexdigest()
    meta = ModelPublic(
        id=sha[:16],
        name="cube",
        vertices=8,
        faces=12,
        bounds=[[0, 0, 0], [1, 1, 1]],
        textured=False,
        format="obj",
        size_bytes=len(CUBE_OBJ),
        sha256=sha,
        created_at=datetime.now(UTC),
    )
    r.hset(KEYS.model(meta.id), "meta", meta.model_dump_json())
    r.set(KEYS.model_data(meta.id), CUBE_OBJ)
    return done, waiting, meta.id, CUBE_OBJ


def test_an_older_deployments_bytes_are_served_then_migrated(svc: Svc) -> None:
    from service.store import ModelStore
    from service.store.blobs.migrate import BlobMigration

    done, waiting, model_id, mesh = _legacy_records(svc.r)
    store = JobStore(svc.r, KEYS, 600, blobs=svc.blobs)
    models = ModelStore(svc.r, KEYS, blobs=svc.blobs)
    url = f"/v1/estimates/{done}/artifacts/difference"
    before = svc.client.get(url)
    assert before.status_code == 200 and before.content == ARTIFACTS["difference"]
    assert store.get_image(store.get(waiting)) == png()  # type: ignore[arg-type]
    assert models.data(model_id) == mesh
    assert store.get(done).result == LEGACY_RESULT  # type: ignore[union-attr]

    report = BlobMigration(svc.r, KEYS, svc.blobs).run()
    assert (report.images, report.artifacts, report.models, report.results) == (1, 1, 1, 1)
    assert svc.r.hget(KEYS.job(done), "result") is None  # compressed into result_z
    assert store.get(done).result == LEGACY_RESULT  # type: ignore[union-attr]
    assert not svc.r.exists(KEYS.job_artifact(done, "difference"), KEYS.job_image(waiting))
    assert not svc.r.exists(KEYS.model_data(model_id))
    after = svc.client.get(url)
    assert after.content == before.content and after.headers["etag"] == before.headers["etag"]
    assert store.get_image(store.get(waiting)) == png()  # type: ignore[arg-type]
    assert models.data(model_id) == mesh
    again = BlobMigration(svc.r, KEYS, svc.blobs).run()  # resumable: nothing left to move
    assert (again.images, again.artifacts, again.models, again.dropped, again.results) == (0,) * 5


def test_the_migrate_blobs_command(svc: Svc, redis_server) -> None:  # type: ignore[no-untyped-def]
    done, _waiting, _model_id, _mesh = _legacy_records(svc.r)
    env = {**os.environ, **svc.env, "PROXPOSE_REDIS_URL": redis_server.url(DB)}
    env["PROXPOSE_DATA_DIR"] = str(get_settings().data_dir)
    proc = subprocess.run(
        [sys.executable, "-m", "worker.cli", "migrate-blobs"],
        env=env,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "1 images, 1 artifacts, 1 model files" in proc.stdout
    assert "1 results compressed" in proc.stdout
    assert "swept:" in proc.stdout
    assert not svc.r.exists(KEYS.job_artifact(done, "difference"))
    assert svc.client.get(f"/v1/estimates/{done}/artifacts/difference").status_code == 200
