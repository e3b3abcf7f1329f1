"""The typed client's track calls (``submit_track``, ``get_track``, ``track_events``,
``wait_track``, ``cancel_track``, ``track_artifact``, ``track_json``) against a real API process
on a real Redis, and one track run to the end by a real worker process."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import redis
from conftest import WorkerPool, log_tails
from service_api_helpers import base_request, png
from test_client import api_url, client_env  # noqa: F401 (the API process fixtures)

from schemas.settings import get_settings
from schemas.track_jobs import TrackCreate
from service.client import BadRequest, Client, Conflict, NotFound, PayloadTooLarge, WaitTimeout
from service.store import Keys


@pytest.fixture
def api(api_url: str) -> Iterator[Client]:  # noqa: F811
    with Client(api_url, timeout_s=10.0) as client:
        yield client


def test_submit_get_and_cancel_a_track(api: Client, tmp_path: Path) -> None:
    first = tmp_path / "a.png"
    first.write_bytes(png())
    job = api.submit_track([first, png()], TrackCreate.model_validate(base_request()))
    assert job.status == "queued" and len(job.id) == 32
    assert job.frame_names == ["a.png", "image"]
    assert job.progress.frames_total == 2 and job.progress.frames_done == 0
    shown = api.get_track(job.id)
    assert shown.id == job.id and shown.request is not None
    with pytest.raises(WaitTimeout) as late:
        api.wait_track(job.id, timeout_s=0.3, poll_s=0.1)
    assert late.value.job.status == "queued" and "track" in str(late.value)
    assert api.cancel_track(job.id).status == "cancelled"
    events = list(api.track_events(job.id))
    assert events[0].kind == "status" and events[-1].kind == "end"
    assert events[-1].job is not None and events[-1].job.status == "cancelled"
    assert api.wait_track(job.id).status == "cancelled"
    with pytest.raises(Conflict):
        api.cancel_track(job.id)
    with pytest.raises(NotFound):
        api.track_json(job.id)
    with pytest.raises(NotFound):
        api.get(job.id)  # a track is not an estimate


def test_a_retried_track_returns_the_same_job(api: Client) -> None:
    first = api.submit_track([png(), png()], base_request(), idempotency_key="client-track-1")
    again = api.submit_track([png(), png()], base_request(), idempotency_key="client-track-1")
    assert again.id == first.id


def test_bad_tracks_raise_with_the_field(api: Client) -> None:
    with pytest.raises(BadRequest) as wrong_size:
        api.submit_track([png(), png(32, 32)], base_request())
    assert wrong_size.value.errors[0].loc == ["body", "frames", 1]
    truth = base_request()["initial_pose"]
    with pytest.raises(BadRequest) as mismatch:
        api.submit_track([png(), png()], base_request(ground_truth=[truth]))
    assert mismatch.value.errors[0].loc == ["body", "request", "ground_truth"]
    with pytest.raises(PayloadTooLarge) as many:
        api.submit_track([png()] * 501, base_request())
    assert many.value.errors[0].loc == ["body", "frames"]


@pytest.mark.slow
def test_a_worker_runs_a_track_the_client_follows_to_its_artifacts(
    api: Client,
    client_env: dict[str, str],  # noqa: F811
    tmp_path_factory: pytest.TempPathFactory,
    variant: str,
) -> None:
    """Two ray-traced frames of the demo satellite (test_service_tracks_worker's sequence), a
    real ``proxpose worker`` process: the client streams one progress event per frame, and
    the result, track.json and the artifacts come back typed."""
    from test_service_tracks_worker import make_frames

    frames, request = make_frames(tmp_path_factory.mktemp("client-track"))
    frames, request["ground_truth"] = frames[:2], request["ground_truth"][:2]
    logs = Path(client_env["PROXPOSE_DATA_DIR"])
    r = redis.Redis.from_url(client_env["PROXPOSE_REDIS_URL"])
    pool = WorkerPool(client_env, logs, r, Keys(get_settings().redis_prefix).estimate_queue)
    pool.ensure(1)
    try:
        job = api.submit_track(frames, request)
        events = list(api.track_events(job.id))
        done = api.wait_track(job.id, timeout_s=600)
    finally:
        pool.terminate_all()
    assert done.status == "succeeded", (done.error, log_tails(logs))
    progress = [e.progress for e in events if e.progress is not None]
    assert [p.frames_done for p in progress] == [1, 2]
    assert [p.frame.image for p in progress] == [f.name for f in frames]
    assert events[-1].job is not None and events[-1].job.status == "succeeded"
    assert done.result is not None and api.track_json(job.id) == done.result
    assert api.track_artifact(job.id, "trajectory")[:4] == b"\x89PNG"
    table = api.track_artifact(job.id, "track.csv").decode().splitlines()
    assert "image" in table[0].split(",") and len(table) == 3
