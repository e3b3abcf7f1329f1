"""Process settings, read from the environment with the prefix ``PROXPOSE_``.

Read through :func:`get_settings` (cached); tests clear the cache instead of patching a global.
Every field is documented in the README's settings table (the descriptions here are the source).
"""

from __future__ import annotations

import os
import re
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from schemas.names import DEFAULT_MAX_IMAGE_PIXELS, DEFAULT_MAX_MODEL_FACES

#: Seconds in a day, for the retention default.
_DAY_S = 24 * 3600
_MIB = 1024 * 1024
#: Names of API keys (who owns jobs and models): letters, digits, '_', '.', '-'.
KEY_NAME_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
#: Shortest API key accepted, characters (a random key of 32+ characters is recommended).
API_KEY_MIN_CHARS = 16


def _parse_keys(value: object) -> object:
    """``"alice:KEY1,bob:KEY2"`` → {"alice": "KEY1", "bob": "KEY2"} (a dict passes through)."""
    if not isinstance(value, str):
        return value
    keys: dict[str, str] = {}
    for entry in filter(None, (part.strip() for part in value.split(","))):
        name, sep, key = entry.partition(":")
        if not sep:
            raise ValueError(f"entry '{name[:12]}…' is not name:key")
        keys[name.strip()] = key.strip()
    return keys


def _check_keys(keys: dict[str, str]) -> dict[str, str]:
    for name, key in keys.items():
        if not re.match(KEY_NAME_PATTERN, name):
            raise ValueError(f"key name '{name}' must match {KEY_NAME_PATTERN}")
        if len(key) < API_KEY_MIN_CHARS or not key.isprintable() or " " in key:
            raise ValueError(
                f"the key of '{name}' must be at least {API_KEY_MIN_CHARS} printable characters "
                "without spaces"
            )
    return keys


ApiKeys = Annotated[dict[str, str], NoDecode]


class Settings(BaseSettings):
    """Settings shared by the CLI, the API and the workers."""

    # hide_input_in_errors: a rejected setting may be an API key, which must not reach a log
    model_config = SettingsConfigDict(
        env_prefix="PROXPOSE_", extra="ignore", hide_input_in_errors=True
    )

    # -- engine
    data_dir: Path = Field(
        default=Path("data"),
        description="Where the embedded Redis keeps its data, and where each worker caches model "
        "files and the demo model.",
    )
    variant: Literal["auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"] = Field(
        default="auto",
        description="Mitsuba variant; 'auto' takes cuda_ad_rgb when Dr.Jit finds a CUDA "
        "device, else llvm_ad_rgb when an LLVM ≥ 16 is found, else scalar_rgb.",
    )
    llvm_path: Path | None = Field(
        default=None, description="libLLVM shared library for Dr.Jit (found automatically)."
    )
    parsed_model_cache: str = Field(
        default="auto",
        description="Where a model file's parse is kept for the next process, so that a GLB, PLY "
        "or STL is parsed once (not by every `proxpose estimate`): a directory, 'auto' for "
        "proxpose/parsed-models under $XDG_CACHE_HOME (default ~/.cache), or 'off'.",
    )

    # -- Redis and the queue
    redis_url: str | None = Field(
        default=None,
        description="Redis to use, e.g. redis://host:6379/0. Unset, `proxpose serve` starts an "
        "embedded one, and the API and `proxpose worker` connect to that one "
        "(redis://127.0.0.1:<embedded_redis_port>/0).",
    )
    redis_prefix: str = Field(
        default="proxpose",
        pattern=r"^[A-Za-z0-9_.-]{1,40}$",
        description="Prefix of every Redis key and queue name this service uses, so that several "
        "deployments can share one Redis.",
    )
    embedded_redis_port: int = Field(
        default=6380,
        ge=1,
        le=65535,
        description="TCP port (on 127.0.0.1) of the Redis that `proxpose serve` embeds.",
    )
    job_timeout_s: int = Field(
        default=900,
        ge=10,
        le=7 * _DAY_S,
        description="An estimate running longer than this is stopped and fails with 'timeout'.",
    )
    render_timeout_s: float = Field(
        default=60.0,
        gt=0.0,
        le=3600.0,
        description="How long POST /v1/renders waits for a worker's render before answering 504.",
    )
    retention_s: int = Field(
        default=7 * _DAY_S,
        ge=60,
        description="How long finished jobs, their results and artifacts are kept (the job in "
        "Redis, its blobs in the blob store).",
    )

    # -- blobs (reference images, artifacts, model files)
    blob_store: str | None = Field(
        default=None,
        description="Where the bytes go (reference images, artifact PNGs, model files): "
        "file:///path (a directory) or s3://bucket/prefix (S3-compatible, with s3_endpoint_url "
        "for MinIO and others). Unset: file://<data_dir>/blobs. API and workers must share it.",
    )
    s3_endpoint_url: str | None = Field(
        default=None,
        pattern=r"^https?://\S+$",
        description="Endpoint of an S3-compatible store, e.g. http://minio:9000 (unset: AWS).",
    )
    s3_region: str | None = Field(default=None, description="Region of the S3 bucket.")
    s3_access_key_id: str | None = Field(
        default=None,
        repr=False,
        description="S3 access key (unset: boto3's chain, e.g. AWS_ACCESS_KEY_ID or a role).",
    )
    s3_secret_access_key: str | None = Field(
        default=None, repr=False, description="S3 secret key (unset: boto3's chain)."
    )
    blob_timeout_s: float = Field(
        default=10.0,
        gt=0.0,
        le=300.0,
        description="Connect and read timeout of one S3 request, s.",
    )
    blob_sweep_s: int = Field(
        default=600,
        ge=5,
        le=_DAY_S,
        description="Period of the blob sweep (one worker per period deletes the blobs of "
        "ended, expired and deleted jobs and models), s.",
    )

    # -- HTTP
    host: str = Field(default="127.0.0.1", description="Address `proxpose serve` binds the API to.")
    port: int = Field(default=8000, ge=1, le=65535, description="Port of the API.")
    workers: int = Field(
        default=1, ge=0, le=64, description="Workers `proxpose serve` starts beside the API."
    )
    api_processes: int = Field(
        default=1,
        ge=1,
        le=16,
        description="API processes `proxpose serve` runs (uvicorn --workers); with more than "
        "one, /metrics adds up the HTTP figures of all of them (Prometheus multiprocess mode, "
        "files under <data_dir>/prometheus).",
    )
    worker_nice: int = Field(
        default=10,
        ge=0,
        le=19,
        description="Scheduling niceness a worker process takes on start (0 = unchanged): "
        "estimates are batch work, so on a machine shared with the API the API's answers come "
        "first.",
    )
    max_image_bytes: int = Field(
        default=64 * _MIB, ge=1024, description="Largest reference image upload, bytes."
    )
    max_image_pixels: int = Field(
        default=DEFAULT_MAX_IMAGE_PIXELS,
        ge=256,
        description="Largest reference image, pixels; checked from the header before decoding.",
    )
    max_model_bytes: int = Field(
        default=128 * _MIB, ge=1024, description="Largest model file upload, bytes."
    )
    max_model_faces: int = Field(
        default=DEFAULT_MAX_MODEL_FACES,
        ge=1,
        description="Most triangles a model may have (checked on upload and when a worker loads "
        "it).",
    )
    max_track_frames: int = Field(
        default=500, ge=1, description="Most frames one track (`POST /v1/tracks`) may have."
    )
    max_track_bytes: int = Field(
        default=64 * _MIB,
        ge=1024,
        description="Largest total size of one track's frames, bytes (each frame also obeys "
        "max_image_bytes).",
    )
    max_request_json_bytes: int = Field(
        default=_MIB,
        ge=1024,
        le=_MIB,
        description="Largest `request` JSON of an estimate, bytes (as a form field Starlette "
        "caps it at 1 MiB).",
    )

    # -- access control and limits per key
    api_keys: ApiKeys = Field(
        default_factory=dict,
        repr=False,
        description="API keys as 'name:key,name:key'. When any key (here or in admin_api_keys) "
        "is set, every /v1 route and page needs 'Authorization: Bearer <key>'; a key sees only "
        "the jobs and models of its name.",
    )
    admin_api_keys: ApiKeys = Field(
        default_factory=dict,
        repr=False,
        description="Admin API keys, 'name:key,...': they see and manage every job and model.",
    )
    submissions_per_minute: float = Field(
        default=120.0,
        ge=0.0,
        description="Sustained submissions (POST of estimates, renders, models) per minute per "
        "key; 0 = unlimited. Above it: 429 with Retry-After.",
    )
    inline_submissions: bool = Field(
        default=True,
        description="Store a small estimate submission (image up to 1 MiB, file blob store) "
        "on the API's event loop while Redis answers within 1 s, instead of in its thread "
        "pool: a burst of submissions then finishes in turn instead of all at its end.",
    )
    submission_burst: int = Field(
        default=30, ge=1, description="Submissions a key may make at once before the rate applies."
    )
    max_active_jobs_per_key: int = Field(
        default=100,
        ge=0,
        description="Queued plus running estimates per key; 0 = unlimited. Above it: 429.",
    )
    max_models_per_key: int = Field(
        default=100, ge=0, description="Models a key may register; 0 = unlimited. Above it: 403."
    )
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Origins allowed to call the API from a browser (CORS), comma-separated; "
        "empty = CORS off.",
    )

    # -- crash safety
    job_lease_s: float = Field(
        default=30.0,
        ge=2.0,
        le=600.0,
        description="A running estimate whose worker has not renewed its lease for this long "
        "is taken as lost (killed, crashed) and queued again.",
    )
    job_max_attempts: int = Field(
        default=3,
        ge=1,
        le=20,
        description="Times an estimate is started at most; after that many lost workers it "
        "fails with 'worker_lost'.",
    )
    log_format: Literal["auto", "json", "text"] = Field(
        default="auto",
        description="Log lines of the API and workers (uvicorn's own lines included): JSON "
        "objects (with job ids) or text; auto: text when stderr is a terminal (make run in a "
        "shell), JSON otherwise (a service manager, a container, a pipe).",
    )

    sse_keepalive_s: float = Field(
        default=15.0,
        gt=0.0,
        le=300.0,
        description="Interval of keep-alive comments on idle event streams, s.",
    )
    shutdown_grace_s: float = Field(
        default=10.0,
        ge=0.0,
        le=3600.0,
        description="On Ctrl-C, how long `proxpose serve` lets running jobs finish before it "
        "stops them (they go back to the queue).",
    )

    @field_validator("api_keys", "admin_api_keys", mode="before")
    @classmethod
    def _keys_from_text(cls, value: object) -> object:
        return _parse_keys(value)

    @field_validator("api_keys", "admin_api_keys")
    @classmethod
    def _keys_valid(cls, value: dict[str, str]) -> dict[str, str]:
        return _check_keys(value)

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _origins_from_text(cls, value: object) -> object:
        if isinstance(value, str):
            return [o.strip().rstrip("/") for o in value.split(",") if o.strip()]
        return value

    @field_validator("blob_store")
    @classmethod
    def _blob_store_url(cls, value: str | None) -> str | None:
        if value is None or not value.strip():
            return None
        value = value.strip()
        if value.startswith("file://") and len(value) > len("file://"):
            return value
        if re.match(r"^s3://[a-z0-9][a-z0-9.-]{1,61}[a-z0-9](/[^\s]*)?$", value):
            return value
        raise ValueError("must be file:///path/to/dir or s3://bucket[/prefix]")

    @model_validator(mode="after")
    def _keys_distinct(self) -> Settings:
        entries = [*self.api_keys.items(), *self.admin_api_keys.items()]
        if len({key for _, key in entries}) != len(entries):
            raise ValueError("the same API key is given twice (keys must be distinct)")
        if set(self.api_keys) & set(self.admin_api_keys):
            raise ValueError("a key name is both in api_keys and admin_api_keys")
        return self

    @property
    def auth_enabled(self) -> bool:
        """Whether API keys are required (some key is configured)."""
        return bool(self.api_keys or self.admin_api_keys)

    def effective_blob_store(self) -> str:
        """``blob_store``, or the directory ``blobs`` under ``data_dir`` when it is unset."""
        return self.blob_store or f"file://{Path(self.data_dir).absolute() / 'blobs'}"

    def parsed_model_dir(self) -> Path | None:
        """The directory ``parsed_model_cache`` names, None when it is 'off'."""
        if self.parsed_model_cache == "off":
            return None
        if self.parsed_model_cache != "auto":
            return Path(self.parsed_model_cache).expanduser()
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        return Path(base) / "proxpose" / "parsed-models"

    def effective_redis_url(self) -> str:
        """``redis_url``, or the URL of the embedded Redis when it is unset."""
        return self.redis_url or f"redis://127.0.0.1:{self.embedded_redis_port}/0"


@lru_cache
def get_settings() -> Settings:
    """The process's settings (cached; call ``get_settings.cache_clear()`` after env changes)."""
    return Settings()
