"""The worker process: the RQ job functions the API enqueues by name, and what they need.

:mod:`~worker.jobs.stored` runs a stored job (lease, cancel, retries, failures) whose work
:mod:`~worker.jobs.estimate` (``run_estimate_job``) or :mod:`~worker.jobs.track`
(``run_track_job``: an image sequence) gives it,
:mod:`~worker.jobs.render` one render (``run_render_job``), :mod:`~worker.jobs.lease` keeps the
running job's lease and the engine's cancel flag, :mod:`~worker.jobs.models` caches model files
on the worker's disk, :mod:`~worker.jobs.context` gives a job its settings and Redis, and
:mod:`~worker.jobs.runner` is ``proxpose worker``.

The API enqueues ``worker.jobs.estimate.run_estimate_job`` and
``worker.jobs.render.run_render_job``. Jobs enqueued by an API from before the restructuring
name ``worker.jobs.run_estimate_job`` and ``worker.jobs.run_render_job``; those names resolve
here (RQ imports this package and reads the attribute) until no such job can remain, see the
README. They resolve lazily, so that the CLI, which imports :mod:`worker.jobs.runner` to build
its parser, does not load RQ, Redis or the engine.
"""

from __future__ import annotations

from typing import Any

#: Old dotted name's attribute → module that holds it now (the pre-restructure RQ names).
_MOVED = {
    "run_estimate_job": "worker.jobs.estimate",
    "run_render_job": "worker.jobs.render",
}


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        import importlib

        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
