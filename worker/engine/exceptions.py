"""Named errors of the engine. Each carries a stable ``code`` the service maps to HTTP answers
and job records; the message says what was wrong in words."""

from __future__ import annotations

from schemas.names import JobErrorCode


class ProxposeError(Exception):
    """Base of every engine error (and of the worker's own, such as a model not registered)."""

    #: The engine's errors carry the codes of ``schemas.names.EngineErrorCode``.
    code: JobErrorCode = "engine_error"


class InvalidInputError(ProxposeError):
    """The request, image or model is unusable as given."""

    code = "invalid_input"


class InvalidPoseError(InvalidInputError):
    """A pose or rotation has the wrong shape or is degenerate."""

    code = "invalid_pose"


class ImageDecodeError(InvalidInputError):
    """The image bytes are not a readable PNG, JPEG or TIFF."""

    code = "invalid_image"


class ImageTooLargeError(InvalidInputError):
    """The image has more pixels than allowed (decompression-bomb guard)."""

    code = "image_too_large"


class ImageSizeMismatchError(InvalidInputError):
    """The image size differs from the camera's width and height."""

    code = "image_size_mismatch"


class ModelLoadError(InvalidInputError):
    """The mesh file cannot be read, or holds no triangles."""

    code = "invalid_model"


class ModelTooLargeError(InvalidInputError):
    """The mesh has more faces than allowed."""

    code = "model_too_large"


class RenderError(ProxposeError):
    """Mitsuba failed to build or render the scene."""

    code = "render_failed"


class EmptyRenderError(ProxposeError):
    """The render at the initial pose shows nothing of the target."""

    code = "empty_render"


class UnlitRenderError(ProxposeError):
    """The target is in view at the initial pose, but the sun lights none of what is seen
    (the render is black but for the ambient light: sun direction, or faces wound inwards)."""

    code = "unlit_render"


class TooFewFeaturesError(ProxposeError):
    """Too few features matched or tracked to constrain the pose."""

    code = "too_few_features"


class EstimationCancelled(ProxposeError):
    """The caller asked the estimate to stop."""

    code = "cancelled"
