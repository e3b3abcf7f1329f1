"""The service's data in Redis: jobs, models, queue access and job statistics.

Shared by the API and the workers (the only thing they share is Redis), so nothing here imports
FastAPI, Mitsuba or OpenCV. Clients are ``redis.Redis`` with ``decode_responses=False`` (RQ needs
bytes); values are decoded here.
"""

from service.store.access import ANONYMOUS, Principal
from service.store.jobs import ActiveJobsLimitError, IdempotencyKeyTaken, JobStore
from service.store.keys import Keys
from service.store.leases import Leases, Reaper
from service.store.models import ModelStore
from service.store.queues import Queues
from service.store.records import JobRecord
from service.store.stats import JobStats

__all__ = [
    "ANONYMOUS",
    "ActiveJobsLimitError",
    "IdempotencyKeyTaken",
    "JobRecord",
    "JobStats",
    "JobStore",
    "Keys",
    "Leases",
    "ModelStore",
    "Principal",
    "Queues",
    "Reaper",
]
