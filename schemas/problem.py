"""Errors of the API: RFC 9457 problem details (``application/problem+json``).

Every error the API answers has this shape, whoever found it (validation, the size limits, the
rate limiter, authentication, a route): ``type``, ``title``, ``status`` and ``detail`` as the RFC
defines them, ``instance`` (the request's path), a stable ``code`` to branch on, and, when the
fault is in named fields, ``errors``: each bad field's location, as FastAPI spells it
(``["body", "request", "camera", "fx"]``), the problem in words and its type.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

#: Media type of a problem details body (RFC 9457 §3).
PROBLEM_MEDIA_TYPE = "application/problem+json"
#: ``type`` URIs are this plus the code: stable identifiers (RFC 9457 §3.1.1 does not require
#: them to be dereferenceable).
PROBLEM_TYPE_PREFIX = "urn:proxpose:problem:"


class FieldError(BaseModel):
    """One bad field: where it is, what is wrong, and the kind of fault."""

    loc: list[str | int] = Field(
        description="Path of the field, e.g. ['body', 'request', 'camera', 'fx'] or "
        "['header', 'Idempotency-Key'].",
        examples=[["body", "request", "camera", "fx"]],
    )
    msg: str = Field(examples=["Input should be greater than 0"])
    type: str = Field(
        description="Kind of fault: pydantic's error types (greater_than, missing, ...) or "
        "ours (too_large, model_not_found, image_size_mismatch, invalid_image, ...).",
        examples=["greater_than"],
    )


class Problem(BaseModel):
    """An error answer (RFC 9457 problem details)."""

    model_config = ConfigDict(extra="allow")  # RFC 9457 §3.2: extension members may follow

    type: str = Field(
        description=f"URI of the kind of problem: '{PROBLEM_TYPE_PREFIX}<code>'.",
        examples=[PROBLEM_TYPE_PREFIX + "validation_error"],
    )
    title: str = Field(description="Short summary of the kind of problem (the HTTP reason).")
    status: int = Field(ge=400, le=599, description="The HTTP status code.")
    detail: str = Field(description="What went wrong with this request, in words.")
    instance: str | None = Field(default=None, description="Path of the request.")
    code: str = Field(
        description="Stable code: validation_error, too_large, unsupported_media_type, "
        "not_found, conflict, unauthorized, forbidden, rate_limited, unavailable, timeout, "
        "internal_error, or a field error's type when one field is at fault.",
        examples=["validation_error"],
    )
    errors: list[FieldError] = Field(
        default_factory=list, description="The bad fields, when the fault is in named fields."
    )


def problem_type(code: str) -> str:
    return PROBLEM_TYPE_PREFIX + code
