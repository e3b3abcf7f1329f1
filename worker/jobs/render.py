"""The render job: one render of a registered model for ``POST /v1/renders`` (RQ entry point).

The API call that enqueued it waits on a Redis list for the outcome; the PNG waits under its own
key. Neither outlives RENDER_RESULT_TTL_S.
"""

from __future__ import annotations

import json
import logging
import time

from rq.timeouts import JobTimeoutException

from schemas.render import RenderRequest
from service.store import JobStats, ModelStore
from service.store.blobs import BlobStoreUnavailable
from worker.engine.exceptions import ProxposeError
from worker.entry import render_png
from worker.jobs.context import job_blobs, job_context
from worker.jobs.models import fetch_model_file

log = logging.getLogger(__name__)

#: How long a render's PNG and outcome wait in Redis for the API call that asked for it, s.
RENDER_RESULT_TTL_S = 300


def run_render_job(render_id: str, model_id: str, request_json: str) -> None:
    """Render once and hand the PNG to the waiting API call (RQ entry point)."""
    settings, r, keys = job_context()
    t0 = time.monotonic()
    outcome: dict[str, object] = {"status": "failed"}
    try:
        request = RenderRequest.model_validate_json(request_json)
        models = ModelStore(r, keys, blobs=job_blobs(settings))
        path = fetch_model_file(models, model_id, settings.data_dir)
        png = render_png(path, request)
        r.set(keys.render_png(render_id), png, ex=RENDER_RESULT_TTL_S)
        outcome = {"status": "succeeded"}
    except ProxposeError as exc:
        outcome["error"] = {"code": exc.code, "message": str(exc)}
    except BlobStoreUnavailable as exc:
        message = f"the blob store ({exc.store}) is unavailable; try again shortly"
        outcome["error"] = {"code": exc.code, "message": message}
    except JobTimeoutException:
        message = f"the render ran longer than {settings.render_timeout_s:g} s"
        outcome["error"] = {"code": "timeout", "message": message}
        raise
    except Exception:
        log.exception("render %s: internal error", render_id)
        message = "internal error in the worker (the traceback is in the worker's log)"
        outcome["error"] = {"code": "internal_error", "message": message}
        raise
    finally:
        pipe = r.pipeline()
        pipe.rpush(keys.render_done(render_id), json.dumps(outcome))
        pipe.expire(keys.render_done(render_id), RENDER_RESULT_TTL_S)
        pipe.execute()
        error = outcome.get("error")
        code = error["code"] if isinstance(error, dict) else None
        JobStats(r, keys).record("render", str(outcome["status"]), time.monotonic() - t0, code)
