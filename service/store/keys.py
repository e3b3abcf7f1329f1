"""Names of every Redis key the service uses, in one place (``<prefix>:…``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Keys:
    """Key names under one prefix (``Settings.redis_prefix``)."""

    prefix: str = "proxpose"

    # -- estimate jobs
    def job(self, job_id: str) -> str:
        """Hash: the job record."""
        return f"{self.prefix}:job:{job_id}"

    def job_image(self, job_id: str) -> str:
        """String: the uploaded reference image of a job of an older deployment (new jobs keep
        it in the blob store), until the job ends."""
        return f"{self.prefix}:job:{job_id}:image"

    def job_artifact(self, job_id: str, name: str) -> str:
        """String: one PNG artifact of a job of an older deployment (now in the blob store)."""
        return f"{self.prefix}:job:{job_id}:artifact:{name}"

    def job_cancel(self, job_id: str) -> str:
        """String: present when a client asked the running job to stop."""
        return f"{self.prefix}:job:{job_id}:cancel"

    def job_lease(self, job_id: str) -> str:
        """String (the attempt number) with a TTL of the lease, renewed by the worker running
        the job; its absence while the job runs means the worker is gone."""
        return f"{self.prefix}:job:{job_id}:lease"

    def job_events(self, job_id: str) -> str:
        """Pub/sub channel of the job's status and progress events."""
        return f"{self.prefix}:job:{job_id}:events"

    @property
    def jobs_index(self) -> str:
        """Sorted set: estimate job ids scored by a creation sequence number (newest =
        highest)."""
        return f"{self.prefix}:jobs"

    def kind_index(self, kind: str) -> str:
        """Sorted set: the ids of the jobs of ``kind`` ('estimate', 'track'), scored like
        ``jobs_index`` (which is the estimates')."""
        return self.jobs_index if kind == "estimate" else f"{self.prefix}:jobs:{kind}"

    @property
    def jobs_seq(self) -> str:
        """Counter behind the creation sequence numbers."""
        return f"{self.prefix}:jobs:seq"

    @property
    def jobs_running(self) -> str:
        """Set: ids of the running jobs (whose leases the reapers check)."""
        return f"{self.prefix}:jobs:running"

    @property
    def jobs_queued(self) -> str:
        """Set: ids of the queued jobs (the orphan sweep checks that RQ still has each)."""
        return f"{self.prefix}:jobs:queued"

    @property
    def orphan_suspects(self) -> str:
        """Hash: job id → RQ id, queued jobs RQ did not have at the last orphan sweep."""
        return f"{self.prefix}:jobs:orphan-suspects"

    @property
    def orphan_sweep_lock(self) -> str:
        """String with a TTL: taken by the one worker that does the orphan sweep of a period."""
        return f"{self.prefix}:jobs:orphan-sweep"

    def idempotency(self, owner: str, key: str) -> str:
        """String: JSON {job_id, fingerprint} of an owner's first POST with this key."""
        return f"{self.prefix}:idempotency:{owner}:{key}"

    # -- per owner (API key name)
    def owner_jobs(self, owner: str, kind: str = "estimate") -> str:
        """Sorted set: the owner's job ids of ``kind`` scored like ``jobs_index``."""
        tail = "" if kind == "estimate" else f":{kind}"
        return f"{self.prefix}:owner:{owner}:jobs{tail}"

    def owner_active(self, owner: str) -> str:
        """Set: the owner's queued and running job ids (the per-key cap counts them)."""
        return f"{self.prefix}:owner:{owner}:active"

    def owner_models(self, owner: str) -> str:
        """Sorted set: ids of the models the owner registered, scored by time."""
        return f"{self.prefix}:owner:{owner}:models"

    def rate(self, owner: str) -> str:
        """String: the owner's submission rate limiter state (GCRA theoretical arrival time)."""
        return f"{self.prefix}:owner:{owner}:rate"

    # -- renders
    def render_png(self, render_id: str) -> str:
        """String: the PNG of a finished render, kept briefly for the waiting API call."""
        return f"{self.prefix}:render:{render_id}:png"

    def render_done(self, render_id: str) -> str:
        """List: the worker pushes the render's outcome (JSON) here; the API blocks on it."""
        return f"{self.prefix}:render:{render_id}:done"

    # -- models
    def model(self, model_id: str) -> str:
        """Hash: the model's metadata."""
        return f"{self.prefix}:model:{model_id}"

    def model_owners(self, model_id: str) -> str:
        """Hash: owner → the name that owner gave the model (built-in models have none)."""
        return f"{self.prefix}:model:{model_id}:owners"

    def model_data(self, model_id: str) -> str:
        """String: the model file's bytes, for a model of an older deployment (now in the
        blob store)."""
        return f"{self.prefix}:model:{model_id}:data"

    @property
    def models_index(self) -> str:
        """Sorted set: model ids scored by registration time."""
        return f"{self.prefix}:models"

    # -- blobs
    @property
    def blob_sweep_lock(self) -> str:
        """String with a TTL: taken by the one worker that sweeps the blob store in a period."""
        return f"{self.prefix}:blobs:sweep"

    @property
    def blob_census(self) -> str:
        """Hash: objects, bytes, swept (deleted so far), at: the blob store as the last sweep
        found it (what /metrics exports)."""
        return f"{self.prefix}:blobs:census"

    # -- statistics
    @property
    def stats(self) -> str:
        """Hash: job counters and duration histogram buckets (see ``store.stats``)."""
        return f"{self.prefix}:stats"

    # -- queues (RQ names, not keys)
    @property
    def estimate_queue(self) -> str:
        return f"{self.prefix}-estimates"

    @property
    def render_queue(self) -> str:
        return f"{self.prefix}-renders"
