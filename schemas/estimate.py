"""The estimate request (REQUEST.json) and its result (result.json)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.camera import Camera
from schemas.lighting import Lighting
from schemas.options import EstimateOptions
from schemas.pose import Pose, PoseOut

StopReason = Literal[
    "step_below_epsilon", "cost_converged", "max_iterations", "stalled", "pnp_converged"
]
Stage = Literal["coarse", "refine"]


class EstimateRequest(BaseModel):
    """Everything the engine needs besides the model and the image (the CLI's REQUEST.json)."""

    model_config = ConfigDict(extra="forbid")

    camera: Camera
    initial_pose: Pose = Field(description="The initial guess of the pose.")
    lighting: Lighting = Field(default_factory=Lighting)
    options: EstimateOptions = Field(default_factory=EstimateOptions)
    ground_truth: Pose | None = Field(
        default=None, description="The true pose, when known: errors are then reported."
    )


class IterationRecord(BaseModel):
    """One iteration of the estimator."""

    iteration: int = Field(description="1-based.")
    stage: Stage
    pose: PoseOut = Field(description="The estimate after this iteration.")
    cost: float = Field(description="Mean squared feature residual at the estimate, px².")
    step_norm: float = Field(description="‖δp‖ of the step taken (0 when rejected).")
    lambda_: float = Field(alias="lambda", description="LM damping λ used (0 for PnP steps).")
    accepted: bool
    features: int = Field(description="Features used in this iteration.")
    renders: int = Field(description="Renders made in this iteration.")
    seconds: float = Field(description="Wall time of this iteration, s.")
    rotation_error_deg: float | None = None
    translation_error: float | None = Field(default=None, description="Scene units.")

    model_config = ConfigDict(populate_by_name=True, serialize_by_alias=True)


class Covariance(BaseModel):
    """Pose covariance: what feature noise explains, plus a term for the model mismatch.

    The statistical part comes from the final Jacobian and residuals: the cluster-robust
    (sandwich) estimate over image cells, or σ² (JᵀWJ)⁻¹ when that is larger. It cannot see a
    mismatch common to the whole image (our render's shading, reflectance or light against the
    camera's): such a difference moves the features together, and the part of it a pose change
    can explain leaves no residual. So the reported covariance adds a model-mismatch term of
    the same shape, (s² − 1)× the statistical one, s = ``mismatch_scale``: measured on
    references rendered with other physics (``proxpose bench --robustness``), actual errors
    were a median 2.1× the statistical σ; with s = 2.5 a median 0.8–0.9× the reported σ, and
    more than 90 % within 3σ.

    The matrix is over p = [δq, δt] (Gibbs increment in the model frame, translation in the
    camera frame); the 1-σ figures convert δq to degrees (an angle is 2|δq| radians).
    """

    matrix: Annotated[list[list[float]], Field(min_length=6, max_length=6)]
    sigma_rotation_deg: list[float] = Field(
        description="1-σ rotation about model x, y, z, deg (feature noise and model mismatch)."
    )
    sigma_translation: list[float] = Field(
        description="1-σ translation x, y, z, scene units (feature noise and model mismatch)."
    )
    statistical_sigma_rotation_deg: list[float] = Field(
        default_factory=list, description="The feature-noise part of sigma_rotation_deg."
    )
    statistical_sigma_translation: list[float] = Field(
        default_factory=list, description="The feature-noise part of sigma_translation."
    )
    mismatch_scale: float = Field(
        default=1.0, description="s: the reported σ is s × the statistical σ (see above)."
    )
    residual_sigma_px: float = Field(description="Residual standard deviation, px.")


class Errors(BaseModel):
    """Errors against the ground truth (when the request had one), as the paper defines them."""

    rotation_deg: float = Field(description="∠ΔR = arccos((tr(RᵀR̂) − 1)/2), degrees.")
    translation: float = Field(description="‖t − t̂‖, scene units.")
    translation_pct_of_range: float = Field(description="100·‖t − t̂‖/‖t‖.")
    speed_score: float = Field(description="‖t − t̂‖/‖t‖ + 2·arccos|⟨q̂, q⟩| (SPEED).")


class EstimateResult(BaseModel):
    """The outcome of one estimate (the CLI's result.json)."""

    pose: PoseOut
    initial_pose: PoseOut
    converged: bool
    reason: StopReason
    iterations: int
    renders: int
    render_cost: float = Field(
        default=0.0,
        description="What the renders cost, in full-resolution renders at the main spp "
        "(pixels × samples per pixel): renders at a coarse level or with fewer samples count "
        "for less.",
    )
    seconds: float
    method: str
    history: list[IterationRecord]
    covariance: Covariance | None = None
    features: int = Field(description="Features used at the final estimate.")
    rms_residual_px: float = Field(description="RMS feature residual at the final estimate, px.")
    alignment_score: float = Field(
        description="Normalised cross-correlation of the final render with the reference over "
        "the target (1 = identical up to tone); a converged estimate needs at least 0.7 (0.3° "
        "off it is about 0.9–0.99, 1° off 0.4–0.95)."
    )
    sun_direction: list[float] | None = Field(
        default=None,
        description="Unit vector from the target towards the sun (camera frame) that the final "
        "render used: the request's, tilted by the fit when options.fit_sun is on.",
    )
    sun_tilt_deg: float = Field(
        default=0.0, description="Angle between sun_direction and the request's, degrees."
    )
    shading_normals: Literal["file", "faceted"] = Field(
        default="file",
        description="Shading normals of the final render: the model file's vertex normals, or "
        "each triangle's own (options.shading_normals 'auto' picks the one that explains the "
        "image better).",
    )
    reflectance_share: float = Field(
        default=0.0,
        description="Share w of a Lommel-Seeliger law (regolith) in the law the reference was "
        "compared under, as the first fit found it (options.reflectance 'fit', or 'auto' on a "
        "smooth body): 0 = the renders' Lambert law, no other fitted or none tried.",
    )
    reflectance_roughness_deg: float = Field(
        default=0.0,
        description="Oren-Nayar roughness sigma (degrees) of that law, as the first fit found "
        "it: 0 = none (a rough surface is brighter than Lambert's where the sun is behind "
        "the camera and flatter towards the limb).",
    )
    errors: Errors | None = None
    initial_errors: Errors | None = None
    timings_s: dict[str, float] = Field(
        default_factory=dict, description="Wall time per part (render, features, ...), s."
    )
    variant: str = Field(description="Mitsuba variant that rendered.")
    artifacts: list[str] = Field(default_factory=list, description="Image files written.")
