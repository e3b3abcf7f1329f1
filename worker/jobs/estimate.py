"""The estimate job (RQ entry point, enqueued by name by the API): run the engine on a stored
estimate (the job's lifecycle is :mod:`worker.jobs.stored`'s)."""

from __future__ import annotations

from schemas.estimate import EstimateRequest, IterationRecord
from schemas.jobs import Progress
from schemas.settings import Settings
from service.store import JobRecord, JobStore, ModelStore
from worker.engine.exceptions import EstimationCancelled, ProxposeError
from worker.entry import run_estimate
from worker.jobs.lease import CancelFlag
from worker.jobs.models import fetch_model_file
from worker.jobs.stored import ProgressReport, cancelled, finish, run_stored_job


def run_estimate_job(job_id: str) -> None:
    """Run the estimate stored as job ``job_id`` (RQ entry point, enqueued by the API)."""
    run_stored_job(job_id, _estimate)


def _estimate(
    store: JobStore, flag: CancelFlag, record: JobRecord, models: ModelStore, settings: Settings
) -> tuple[str, str | None]:
    """Run the engine for a started job and store the outcome; (status, failure code). Errors
    other than a stop requested through ``flag`` propagate (see _failed)."""
    job_id, attempt = record.id, flag.keeper.attempt

    report = ProgressReport(flag, job_id)

    def on_iteration(rec: IterationRecord, max_iterations: int) -> None:
        report(
            Progress(
                iteration=rec.iteration,
                max_iterations=max_iterations,
                cost=rec.cost,
                stage=rec.stage,
            )
        )

    request = EstimateRequest.model_validate_json(record.request)
    image = store.get_image(record)
    if image is None:
        raise ProxposeError("the job's image is missing from the store")
    model_path = fetch_model_file(models, record.model_id, settings.data_dir)
    try:
        result, artifacts = run_estimate(
            model_path, image, request, on_iteration, should_cancel=flag
        )
    except EstimationCancelled as exc:
        return cancelled(store, flag, record, exc)
    finish(
        store,
        record,
        attempt,
        "succeeded",
        result_json=result.model_dump_json(),
        artifacts=artifacts,
    )
    return "succeeded", None
