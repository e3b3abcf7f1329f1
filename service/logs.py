"""Structured logs for the API and the workers: one JSON object per line, with the job's id.

``configure_logging("json")`` puts a JSON formatter on the root logger; fields passed with
``extra={...}`` and the fields of the current :func:`log_context` (a worker sets ``job_id``,
``attempt`` and ``worker`` while it runs a job) appear as keys of the object. A traceback goes
in ``exc``. ``"text"`` keeps the classic one-line format for people reading a terminal;
``"auto"`` picks text when stderr is a terminal, else JSON. uvicorn's loggers (its errors and
access lines) are sent through the same handler, so an API process writes one format; an access
line carries ``method``, ``path``, ``status`` and ``client`` as keys.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from datetime import UTC, datetime
from typing import Any

_context: ContextVar[dict[str, Any]] = ContextVar("proxpose_log_context", default={})  # noqa: B039
#: Attributes every LogRecord has; anything else on a record came from ``extra``.
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime"}
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_HANDLER_NAME = "proxpose"
#: uvicorn's loggers, which it configures with handlers of its own (text) that do not propagate.
UVICORN_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access")


@contextmanager
def log_context(**fields: Any) -> Iterator[None]:
    """Add ``fields`` to every log record made inside the block (this thread/task)."""
    token = _context.set({**_context.get(), **fields})
    try:
        yield
    finally:
        _context.reset(token)


class _ContextFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        for name, value in _context.get().items():
            if not hasattr(record, name):
                setattr(record, name, value)
        return True


class JsonFormatter(logging.Formatter):
    """``{"ts", "level", "logger", "msg", <extra fields>, "exc"}`` on one line."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        for name, value in vars(record).items():
            if name not in _STANDARD and not name.startswith("_"):
                entry[name] = value if isinstance(value, str | int | float | bool) else str(value)
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, ensure_ascii=False)


class _AccessFields(logging.Filter):
    """uvicorn's access record has args (client, method, path, http version, status): as keys."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) == 5:
            client, method, path, _version, status = args
            record.client, record.method, record.path = str(client), str(method), str(path)
            record.status = int(str(status)) if str(status).isdigit() else str(status)
        return True


def resolve_format(fmt: str) -> str:
    """``auto`` → text on a terminal, json elsewhere."""
    if fmt != "auto":
        return fmt
    return "text" if sys.stderr.isatty() else "json"


def adopt_uvicorn_loggers() -> None:
    """Route uvicorn's log lines through the root handler (so they share its format)."""
    for name in UVICORN_LOGGERS:
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            logger.removeHandler(handler)
        logger.propagate = True
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, _AccessFields) for f in access.filters):
        access.addFilter(_AccessFields())


def configure_logging(
    fmt: str, level: int = logging.INFO, quiet: Sequence[str] = (), replace: bool = False
) -> None:
    """One handler on the root logger with the chosen format (``replace``: instead of every
    other root handler, for a process of our own); ``quiet`` loggers log warnings and worse."""
    fmt = resolve_format(fmt)
    handler = logging.StreamHandler()
    handler.setFormatter(JsonFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT))
    handler.addFilter(_ContextFilter())
    handler.set_name(_HANDLER_NAME)
    root = logging.getLogger()
    for old in [h for h in root.handlers if replace or h.get_name() == _HANDLER_NAME]:
        root.removeHandler(old)  # ours from an earlier call; others' (pytest's) stay
    root.addHandler(handler)
    root.setLevel(level)
    for name in quiet:
        logging.getLogger(name).setLevel(logging.WARNING)


def uvicorn_log_config(fmt: str) -> dict[str, Any]:
    """A ``logging.config.dictConfig`` for uvicorn's ``--log-config`` (as JSON): its lines from
    the very first (before the app's lifespan adopts its loggers) in our format."""
    json_fmt = resolve_format(fmt) == "json"
    formatter = {"()": f"{__name__}.JsonFormatter"} if json_fmt else {"format": TEXT_FORMAT}
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"proxpose": formatter},
        "handlers": {
            "proxpose": {
                "class": "logging.StreamHandler",
                "formatter": "proxpose",
                "stream": "ext://sys.stderr",
            }
        },
        "loggers": {
            name: {"handlers": ["proxpose"], "level": "INFO", "propagate": False}
            for name in UVICORN_LOGGERS
        },
    }
