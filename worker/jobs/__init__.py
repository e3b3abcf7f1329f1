"""The worker process's RQ jobs (being split into modules; see the next commit)."""

from worker.jobs.estimate import (
    STOP_NOW,
    model_cache_path,
    register_demo_model,
    run_estimate_job,
    run_render_job,
)

__all__ = [
    "STOP_NOW",
    "model_cache_path",
    "register_demo_model",
    "run_estimate_job",
    "run_render_job",
]
