"""``/v1/tracks`` on a real Redis without workers (nothing here renders): a submission is
stored as one queued job of kind 'track' with its frames in the blob store, idempotency keys
replay it, cancel takes it off the queue and drops its frames; and every bad submission is a
413/422 naming the field (the frame by its index), with nothing enqueued. The track run by a
real worker is in test_service_tracks_worker.py."""

from __future__ import annotations

import json
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient
from rq import Queue
from rq.serializers import JSONSerializer
from service_api_helpers import (
    KEYS,
    SIDE_PX,
    api_client,  # noqa: F401 (the client fixture)
    assert_field_error,
    assert_problem,
    base_request,
    png,
    queued,
    redis_db,  # noqa: F401 (the r fixture)
    response_model_bytes,
    submit,
)

from schemas.settings import get_settings
from service.store.queues import TRACK_JOB

N_FRAMES = 3


def track_request(**changes: Any) -> dict[str, Any]:
    return base_request(**changes)


def frame_files(n: int = N_FRAMES, image: bytes | None = None) -> list[tuple[str, Any]]:
    return [("frames", (f"f{k:03d}.png", image or png(), "image/png")) for k in range(n)]


def submit_track(
    client: TestClient,
    request: dict[str, Any] | str | None = None,
    frames: list[tuple[str, Any]] | None = None,
    headers: dict[str, str] | None = None,
) -> Any:
    request = track_request() if request is None else request
    text = request if isinstance(request, str) else json.dumps(request)
    files = frame_files() if frames is None else frames
    return client.post("/v1/tracks", files=files, data={"request": text}, headers=headers)


def waiting(r: redis.Redis) -> int:
    """Jobs and records a rejected track must not add (queues, both indexes)."""
    return queued(r) + int(r.zcard(KEYS.kind_index("track")))  # type: ignore[arg-type]


def test_submit_answers_202_with_location_and_the_queued_track(
    client: TestClient, r: redis.Redis
) -> None:
    response = submit_track(client)
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/v1/tracks/{job['id']}"
    assert job["status"] == "queued" and job["frames"] == [] and job["result"] is None
    assert job["frame_names"] == [f"f{k:03d}.png" for k in range(N_FRAMES)]
    assert job["progress"] == {"frames_done": 0, "frames_total": N_FRAMES}
    assert "model_id" not in job["request"] and job["request"]["camera"]["width"] == SIDE_PX
    rq_jobs = Queue(KEYS.estimate_queue, connection=r, serializer=JSONSerializer).jobs
    assert [j.func_name for j in rq_jobs] == [TRACK_JOB]
    assert client.get(f"/v1/tracks/{job['id']}").json()["id"] == job["id"]
    # a track is not an estimate: neither listed nor shown there
    assert client.get("/v1/estimates").json()["items"] == []
    assert_problem(client.get(f"/v1/estimates/{job['id']}"), 404, "not_found")
    # and an estimate is not a track
    estimate = submit(client).json()
    assert_problem(client.get(f"/v1/tracks/{estimate['id']}"), 404, "not_found")


def test_idempotency_key_replays_the_same_track(client: TestClient, r: redis.Redis) -> None:
    headers = {"Idempotency-Key": "track-key-1"}
    first = submit_track(client, headers=headers)
    again = submit_track(client, headers=headers)
    assert again.status_code == 202 and again.headers["idempotent-replayed"] == "true"
    assert again.json()["id"] == first.json()["id"]
    assert r.zcard(KEYS.kind_index("track")) == 1
    other = submit_track(client, frames=frame_files(2), headers=headers)
    assert_field_error(other, 422, ("header", "Idempotency-Key"))


def test_a_track_submission_answers_the_bytes_fastapi_would_serialise(
    client: TestClient, r: redis.Redis
) -> None:
    """As for estimates (``submissions.accepted``): the 202's body, new and replayed, is what
    FastAPI's pass over the route's response_model would have written."""
    from service.resources import track_public
    from service.routes import tracks
    from service.store import JobStore

    store = JobStore(r, KEYS, 60, blobs=client.app.state.blobs)  # type: ignore[attr-defined]
    headers = {"Idempotency-Key": "track-bytes-1"}
    for replay in (False, True):
        response = submit_track(client, headers=headers)
        assert (
            response.status_code == 202 and response.headers["content-type"] == "application/json"
        )
        assert ("idempotent-replayed" in response.headers) is replay
        record = store.get(response.json()["id"])
        assert record is not None
        expected = response_model_bytes(tracks.router, tracks.create_track, track_public(record))
        assert response.content == expected
        assert response.headers["location"] == f"/v1/tracks/{record.id}"


def test_cancel_a_queued_track_takes_it_off_the_queue_and_drops_its_frames(
    client: TestClient, r: redis.Redis
) -> None:
    job = submit_track(client).json()
    blobs = client.app.state.blobs  # type: ignore[attr-defined]
    assert len(list(blobs.list(f"jobs/{job['id']}/input/"))) == N_FRAMES
    response = client.delete(f"/v1/tracks/{job['id']}")
    assert response.status_code == 200 and response.json()["status"] == "cancelled"
    assert Queue(KEYS.estimate_queue, connection=r).count == 0
    assert list(blobs.list(f"jobs/{job['id']}/input/")) == []
    assert_problem(client.delete(f"/v1/tracks/{job['id']}"), 409, "job_ended")
    assert_problem(client.get(f"/v1/tracks/{job['id']}/track.json"), 404, "not_found")
    assert_problem(client.get(f"/v1/tracks/{'0' * 32}"), 404, "not_found")


def test_events_of_a_queued_then_cancelled_track_end_with_the_resource(
    client: TestClient,
) -> None:
    job = submit_track(client).json()
    client.delete(f"/v1/tracks/{job['id']}")
    with client.stream("GET", f"/v1/tracks/{job['id']}/events") as stream:
        text = "".join(stream.iter_text())
    assert "event: end" in text, text
    end = json.loads(text.split("event: end\ndata: ", 1)[1].split("\n", 1)[0])
    assert end["id"] == job["id"] and end["status"] == "cancelled" and "frame_names" in end


# ----------------------------------------------------------------------------- refusals
def _frame_of_size(width: int, height: int) -> list[tuple[str, Any]]:
    files = frame_files(2)
    files.append(("frames", ("odd.png", png(width, height), "image/png")))
    return files


BAD_SUBMISSIONS: dict[str, tuple[dict[str, Any], int, tuple[str | int, ...]]] = {
    "no frames": ({"frames": []}, 422, ("body", "frames")),
    "a frame of another size": ({"frames": _frame_of_size(32, 32)}, 422, ("body", "frames", 2)),
    "a frame that is no image": (
        {"frames": [*frame_files(1), ("frames", ("x.png", b"not a png", "image/png"))]},
        422,
        ("body", "frames", 1),
    ),
    "truth not one pose per frame": (
        {
            "request": track_request(
                ground_truth=[{"t": [0, 0, 14], "quaternion": [1, 0, 0, 0]}] * (N_FRAMES - 1)
            )
        },
        422,
        ("body", "request", "ground_truth"),
    ),
    "request not JSON": ({"request": "{"}, 422, ("body", "request")),
    "unknown request field": ({"request": track_request(extra=1)}, 422, ("body", "request")),
    "unknown model": (
        {"request": track_request(model_id="nope")},
        422,
        ("body", "request", "model_id"),
    ),
    "no initial pose": (
        {"request": {k: v for k, v in track_request().items() if k != "initial_pose"}},
        422,
        ("body", "request", "initial_pose"),
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_SUBMISSIONS))
def test_a_bad_submission_is_refused_naming_the_field(
    client: TestClient, r: redis.Redis, case: str
) -> None:
    changes, status, loc = BAD_SUBMISSIONS[case]
    response = submit_track(client, changes.get("request"), changes.get("frames"))
    assert_field_error(response, status, loc)
    assert waiting(r) == 0


def test_too_many_frames_is_413_naming_frames(
    client: TestClient, r: redis.Redis, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_TRACK_FRAMES", "2")
    get_settings.cache_clear()
    error = assert_field_error(submit_track(client), 413, ("body", "frames"))
    assert error["type"] == "too_many_frames" and "limit of 2" in error["msg"]
    assert waiting(r) == 0
    assert submit_track(client, frames=frame_files(2)).status_code == 202


def test_frames_over_the_total_bytes_are_413_naming_frames(
    client: TestClient, r: redis.Redis, monkeypatch: pytest.MonkeyPatch
) -> None:
    one = len(png())
    monkeypatch.setenv("PROXPOSE_MAX_TRACK_BYTES", str(max(1024, 2 * one)))
    get_settings.cache_clear()
    n = max(1024, 2 * one) // one + 1
    error = assert_field_error(submit_track(client, frames=frame_files(n)), 413, ("body", "frames"))
    assert error["type"] == "too_large"
    assert waiting(r) == 0


def test_more_file_parts_than_the_form_parser_takes_is_413(
    client: TestClient, r: redis.Redis
) -> None:
    """Starlette's multipart parser stops at 1,000 file parts with a 400 before our count of
    frames can run: that is a request too large too (413, problem details), nothing enqueued."""
    frames = frame_files(1001, b"\x89PNG")
    error = assert_field_error(submit_track(client, frames=frames), 413, ("body",))
    assert error["type"] == "too_large" and "too many file parts" in error["msg"]
    assert waiting(r) == 0


def test_a_frame_over_the_image_limit_is_413_naming_it(
    client: TestClient, r: redis.Redis, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_IMAGE_BYTES", "1024")
    get_settings.cache_clear()
    big = ("frames", ("big.png", b"\x89PNG" + b"\0" * 4096, "image/png"))
    response = submit_track(client, frames=[*frame_files(1), big])
    assert_field_error(response, 413, ("body", "frames", 1))
    assert waiting(r) == 0


def test_a_body_over_the_track_limit_is_413_before_parsing(
    client: TestClient, r: redis.Redis, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_TRACK_BYTES", "1024")
    get_settings.cache_clear()
    frames = frame_files(1, b"\0" * (2 * 1024 * 1024))
    assert_field_error(submit_track(client, frames=frames), 413, ("body",))
    assert waiting(r) == 0


def test_the_track_page_is_served_for_an_id_and_404_otherwise(client: TestClient) -> None:
    page = client.get(f"/tracks/{'a' * 32}")
    assert page.status_code == 200 and "/static/track.js" in page.text
    assert 'data-job-id="' + "a" * 32 + '"' in page.text
    missing = client.get("/tracks/not-an-id")
    assert missing.status_code == 404 and "No such track" in missing.text
