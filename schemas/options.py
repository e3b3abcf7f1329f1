"""Estimation options: every tunable of the engine, with defaults and a method preset.

``method`` picks a preset; any field the request sets explicitly overrides the preset.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

Method = Literal["default", "paper", "pnp", "fast"]

#: Values each method uses for the fields a request leaves unset.
METHOD_PRESETS: dict[str, dict[str, Any]] = {
    # PnP coarse stage, then the learned-Jacobian LM on KLT-refined corners.
    "default": {},
    # A literal reading of the paper: 4 SIFT features, fixed N_s, features lost in any
    # perturbed view dropped, one Jacobian for all, no coarse stage, no reuse.
    "paper": {
        "coarse": "none",
        "refine_features": "matches",
        "max_features": 4,
        "detector": "sift",
        "min_features": 4,
        "n_samples": 24,
        "jacobian": "common",
        "reuse_jacobian": False,
        "perturbation_scale": 1.0,
        "perturbation_rot_deg": 1.0,
        "perturbation_trans_frac": 0.01,
        "axis_cone_deg": 90.0,
        "robust": False,
        "fit_sun": False,
        "geometric_pass": False,
        "shading_normals": "file",
        "reflectance": "lambert",
        "pyramid": False,
        "window": False,
        "refine_passes": 1,
        "max_iterations": 10,
    },
    # Baseline: PnP refinement on ray-cast correspondences only (no learned Jacobian).
    "pnp": {"coarse": "pnp", "refine_features": "none"},
    # Faster mode: the default pipeline with the Jacobian from ray-cast geometry instead of
    # perturbed renders (no N_s renders), everything else the same.
    "fast": {"jacobian": "analytic"},
}


class EstimateOptions(BaseModel):
    """Tunables of the estimator. Units are in the field names or descriptions."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [{"method": "default"}, {"method": "fast", "max_iterations": 20}]
        },
    )

    method: Method = Field(
        default="default",
        description="'default': PnP coarse stage + learned-Jacobian LM on KLT corners; 'paper': "
        "the paper's configuration read literally (4 features, fixed N_s); 'pnp': PnP "
        "refinement on ray-cast correspondences only (a baseline); 'fast': the default with "
        "the Jacobian from ray-cast geometry instead of perturbed renders.",
    )
    max_iterations: int = Field(default=30, ge=1, le=100, description="Iteration cap (all stages).")
    epsilon: float = Field(
        default=2e-5,
        gt=0.0,
        le=1.0,
        description="Stop when ‖δp‖ < ε, with δp = [rotation increment (rad), translation "
        "increment / range]: dimensionless.",
    )
    cost_tolerance: float = Field(
        default=0.01,
        ge=0.0,
        le=1.0,
        description="Stop when a step lowers the cost, or the linear model predicts it would "
        "lower it, by less than this fraction.",
    )
    n_samples: int = Field(
        default=12, ge=6, le=128, description="N_s: perturbed renders used to learn the Jacobian."
    )
    perturbation_px: float = Field(
        default=3.0,
        gt=0.0,
        le=50.0,
        description="Target image motion of a perturbation, px; sets the rotation and "
        "translation sizes from the target's apparent size unless those are given.",
    )
    perturbation_rot_deg: float | None = Field(
        default=None, gt=0.0, le=20.0, description="Perturbation rotation cap θ, degrees."
    )
    perturbation_trans_frac: float | None = Field(
        default=None,
        gt=0.0,
        le=0.2,
        description="Perturbation translation half-width, as a fraction of the range ‖t‖.",
    )
    axis_cone_deg: float = Field(
        default=180.0,
        gt=0.0,
        le=180.0,
        description="Perturbation axes are drawn uniformly in this cone around the current "
        "attitude's axis; 180 = the whole sphere.",
    )
    perturbation_scale: float = Field(
        default=0.5,
        ge=0.25,
        le=1.0,
        description="Resolution of the perturbation renders relative to the image (Jacobian "
        "learning needs less detail than the residuals).",
    )
    reuse_jacobian: bool = Field(
        default=True,
        description="Reuse the learned Jacobian across refinement iterations while the pose "
        "moves little (the features stay the same reference corners).",
    )
    jacobian: Literal["per_feature", "common", "analytic"] = Field(
        default="per_feature",
        description="'per_feature': fit each feature's two rows from the views it was tracked "
        "in; 'common': drop features lost in any view (the paper); 'analytic': from ray-cast "
        "geometry, no perturbed renders (the 'fast' method).",
    )
    refine_passes: int = Field(
        default=2,
        ge=1,
        le=5,
        description="Passes of the refinement: each later pass starts at the pose the previous "
        "one ended at and makes its features, tone match, sharpness match and Jacobian afresh "
        "there (with the fitted sun), instead of keeping those of a render up to a few tenths "
        "of a degree off.",
    )
    geometric_pass: bool = Field(
        default=True,
        description="After the learned-Jacobian passes, one more LM pass on the last pass's "
        "features with the Jacobian from the model's geometry (ray casts, as 'fast' uses), "
        "each step checked by a trial render; kept only when the features fit its pose "
        "better. Learned rows miss the near-cancellation of a weakly seen direction (a flat "
        "target's out-of-plane rotation against a lateral shift) and stop short there.",
    )
    geometric_recheck_deg: float = Field(
        default=0.15,
        ge=0.0,
        le=10.0,
        description="When the geometric pass is kept and turned the attitude by more than this "
        "(degrees), the learned passes had stopped short: one more learned pass (features made "
        "afresh) and geometric pass run from its pose, up to twice. 0: never.",
    )
    reflectance: Literal["auto", "lambert", "fit"] = Field(
        default="auto",
        description="Reflectance law of the renders: 'lambert'; 'fit' = fit the share of a "
        "Lommel-Seeliger law (regolith, which does not darken towards the limb) and an "
        "Oren-Nayar roughness (a rough surface, brighter towards the sun's side) from the "
        "image when the features are made, and compare with the reference as a Lambertian "
        "surface would show it; 'auto' = 'fit' on a smooth body (a shading normal that turns "
        "from pixel to pixel almost everywhere it is lit and stays near its triangles' "
        "normals: an asteroid, a moon), else "
        "'lambert' (on spacecraft the fit costs accuracy: a crease's gain step is placed at "
        "the estimated pose, and a few flat faces do not tell the law from their albedos).",
    )
    fit_sun: bool = Field(
        default=True,
        description="Solve for a tilt of the sun (up to 10° from the request's direction) "
        "together with the pose in the refinement: shading features then stop pulling the "
        "pose when the request's sun direction is a few degrees off.",
    )
    shading_normals: Literal["auto", "file", "faceted"] = Field(
        default="auto",
        description="Shading normals of the renders: 'file' = the model's vertex normals "
        "(faceted where it has none); 'faceted' = each triangle's own normal; 'auto' = after "
        "the coarse stage, render both and keep the one that explains the image better (a "
        "model tessellated differently from the surface that made the image shades "
        "differently, and shading moves features).",
    )
    pyramid: bool = Field(
        default=True,
        description="Coarse to fine: the coarse stage and every refinement pass but the last "
        "work on the image reduced by a power of two (short side ≥ 240 px, target ≥ 120 px "
        "across), the last pass at full resolution.",
    )
    window: bool = Field(
        default=True,
        description="Once the coarse stage has placed the target, the refinement renders and "
        "processes only a window around it (a square about 1.2× the target's bounding sphere "
        "across, when that leaves at least a quarter of the image out) instead of the whole image.",
    )
    coarse: Literal["pnp", "none"] = Field(
        default="pnp",
        description="Coarse stage before the Jacobian LM: PnP on ray-cast correspondences.",
    )
    attitude_search: bool = Field(
        default=False,
        description="Before the coarse stage, turn the target about its centre to the attitude "
        "whose render, moved onto the reference's silhouette, best matches it (turns of 6-18°, "
        "then 3-6° and 1.5-3° about the best: 158 renders at the coarse level, ~1 s at 512²), "
        "and place it there. For a start far off in attitude, where descriptor matches fail (a "
        "tracker's lost frame uses it when the full estimate from the prediction fails); not "
        "the default (bench: a wash on starts up to 20° off, for ~1 s more). Skipped when the "
        "frame cuts the target or the camera is inside the model's bounding sphere (terrain).",
    )
    refine_features: Literal["klt", "matches", "none"] = Field(
        default="klt",
        description="Features of the LM stage: 'klt' = reference corners tracked into the "
        "render; 'matches' = descriptor matches each iteration; 'none' = no LM stage.",
    )
    detector: Literal["both", "sift", "orb"] = Field(
        default="both", description="Keypoint detector: SIFT, ORB, or both pooled."
    )
    ratio: float = Field(default=0.8, gt=0.0, lt=1.0, description="Lowe ratio-test threshold.")
    max_features: int = Field(default=600, ge=3, le=5000, description="Features used at most.")
    min_features: int = Field(default=6, ge=3, le=1000, description="Fewer fails the estimate.")
    robust: bool = Field(
        default=True, description="Pose-consistent outlier rejection (RANSAC and IRLS weights)."
    )
    lambda_init: float = Field(default=1e-3, gt=0.0, le=1e6, description="Initial LM damping λ.")
    spp: int = Field(
        default=16,
        ge=1,
        le=1024,
        description="Samples per pixel of the main renders (the coarse stage's: see coarse_spp).",
    )
    coarse_spp: int | None = Field(
        default=None,
        ge=1,
        le=1024,
        description="Samples per pixel of the coarse stage's renders; null: spp at full "
        "resolution, spp·level² at a reduced level (as many samples per unit of image area; at "
        "least perturbation_spp: the reference is area-averaged to that level, and so is the "
        "noise). At full resolution fewer are cheaper but noisier: 4 at 192×144 px, and for a "
        "terrain half out of frame, left the estimate 0.4-0.6° off.",
    )
    perturbation_spp: int = Field(
        default=4, ge=1, le=1024, description="Samples per pixel, perturbation renders."
    )
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="Seed of all random choices.")

    def resolved(self) -> EstimateOptions:
        """These options with the method preset filled into every field left unset."""
        preset = METHOD_PRESETS[self.method]
        values = self.model_dump()
        for name, value in preset.items():
            if name not in self.model_fields_set:
                values[name] = value
        return EstimateOptions.model_validate(values)
