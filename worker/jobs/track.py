"""The track job (RQ entry point, enqueued by name by the API): track a stored image sequence
with :func:`worker.tracking.run_track`, as ``proxpose track`` does, reporting every frame (the
job's progress holds the frames so far; its event carries the one just done). The job's
lifecycle (lease, cancel, retries, failures) is :mod:`worker.jobs.stored`'s.

Artifacts: ``trajectory`` (the CLI's plot), ``track.csv`` and ``overlay_<k>`` (the frame in
red, the render at its pose in blue) for up to OVERLAY_FRAMES_MAX frames spread over the
sequence, the lost and re-initialised ones first.
"""

from __future__ import annotations

from schemas.settings import Settings
from schemas.track import TrackFrame, TrackRequest
from schemas.track_jobs import TrackProgressEvent, TrackState
from service.store import JobRecord, JobStore, ModelStore
from worker.engine.exceptions import EstimationCancelled, ProxposeError
from worker.jobs.lease import CancelFlag
from worker.jobs.models import fetch_model_file
from worker.jobs.stored import ProgressReport, cancelled, finish, run_stored_job
from worker.tracking import FrameFile, run_track, track_csv, trajectory_png
from worker.tracking_overlays import overlay_indices, overlays

#: Most frames that get an overlay artifact (each costs a render at the frame's pose).
OVERLAY_FRAMES_MAX = 24


def run_track_job(job_id: str) -> None:
    """Run the track stored as job ``job_id`` (RQ entry point, enqueued by the API)."""
    run_stored_job(job_id, _track)


def _frames(store: JobStore, record: JobRecord) -> list[FrameFile]:
    frames = []
    for k, ref in enumerate(record.inputs):
        data = store.get_input(record, k)
        if data is None:
            raise ProxposeError(f"frame {k} ({ref['name']}) is missing from the store")
        frames.append(FrameFile(ref["name"], data))
    return frames


def _track(
    store: JobStore, flag: CancelFlag, record: JobRecord, models: ModelStore, settings: Settings
) -> tuple[str, str | None]:
    """Track the frames of a started job and store the outcome; (status, failure code)."""
    report = ProgressReport(flag, record.id)
    state = TrackState(frames_total=len(record.inputs))

    def on_frame(frame: TrackFrame) -> None:
        state.frames.append(frame)
        state.frames_done = len(state.frames)
        event = TrackProgressEvent(
            frames_done=state.frames_done, frames_total=state.frames_total, frame=frame
        )
        report(state, event)

    request = TrackRequest.model_validate_json(record.request)
    frames = _frames(store, record)
    model_path = fetch_model_file(models, record.model_id, settings.data_dir)
    try:
        result = run_track(model_path, frames, request, on_frame, should_cancel=flag)
        chosen = overlay_indices(result, OVERLAY_FRAMES_MAX)
        artifacts = {
            "trajectory": trajectory_png(result),
            "track.csv": track_csv(result).encode(),
            **overlays(model_path, frames, request, result, chosen, flag),
        }
    except EstimationCancelled as exc:
        return cancelled(store, flag, record, exc)
    finish(
        store,
        record,
        flag.keeper.attempt,
        "succeeded",
        result_json=result.model_dump_json(),
        artifacts=artifacts,
    )
    return "succeeded", None
