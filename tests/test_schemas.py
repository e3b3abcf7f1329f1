"""The pydantic contract (schemas/): what requests are accepted, normalised and rejected."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from pydantic import ValidationError

from schemas.camera import Camera
from schemas.estimate import EstimateRequest, EstimateResult
from schemas.lighting import Lighting
from schemas.options import METHOD_PRESETS, EstimateOptions
from schemas.pose import Pose
from schemas.render import RenderRequest

ROT_Z_90 = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
CAMERA = {"width": 320, "height": 240, "fx": 400.0, "fy": 400.0, "cx": 159.5, "cy": 119.5}


def _errors(exc: pytest.ExceptionInfo[ValidationError]) -> str:
    return json.dumps(exc.value.errors(include_url=False, include_input=False), default=str)


# -- pose ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "attitude",
    [{"q": [0.1, 0.2, 0.3]}, {"quaternion": [1.0, 0.0, 0.0, 0.0]}, {"R": ROT_Z_90}],
)
def test_pose_accepts_each_single_attitude_form(attitude: dict[str, Any]) -> None:
    pose = Pose(t=[0.0, 0.0, 10.0], **attitude)
    given = [k for k in ("q", "quaternion", "R") if getattr(pose, k) is not None]
    assert given == list(attitude)


@pytest.mark.parametrize(
    "attitude",
    [
        {},
        {"q": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]},
        {"q": [0.0, 0.0, 0.0], "R": ROT_Z_90},
        {"quaternion": [1.0, 0.0, 0.0, 0.0], "R": ROT_Z_90},
        {"q": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0], "R": ROT_Z_90},
    ],
)
def test_pose_needs_exactly_one_attitude(attitude: dict[str, Any]) -> None:
    with pytest.raises(ValidationError, match="exactly one of"):
        Pose(t=[0.0, 0.0, 10.0], **attitude)


def test_quaternion_is_normalised_within_tolerance() -> None:
    pose = Pose(t=[0, 0, 1], quaternion=[1.0005, 0.0, 0.0, 0.0])
    assert pose.quaternion == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-15)
    s = 1.0 / math.sqrt(2.0) * 0.9995
    pose = Pose(t=[0, 0, 1], quaternion=[s, 0.0, s, 0.0])
    assert math.hypot(*pose.quaternion) == pytest.approx(1.0, abs=1e-15)
    for bad in ([1.002, 0, 0, 0], [0.998, 0, 0, 0], [0, 0, 0, 0], [2, 0, 0, 0]):
        with pytest.raises(ValidationError, match="unit norm"):
            Pose(t=[0, 0, 1], quaternion=bad)


def test_rotation_matrix_must_be_orthonormal_and_proper() -> None:
    Pose(t=[0, 0, 1], R=[[1.0, 0.0, 0.0005], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # within 1e-3
    with pytest.raises(ValidationError, match="orthonormal"):
        Pose(t=[0, 0, 1], R=[[1.0, 0.0, 0.01], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValidationError, match="orthonormal"):
        Pose(t=[0, 0, 1], R=[[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValidationError, match="reflection"):
        Pose(t=[0, 0, 1], R=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    with pytest.raises(ValidationError, match="reflection"):
        Pose(t=[0, 0, 1], R=[[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(
    "R", [[[1, 0, 0], [0, 1, 0]], [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]], [[1, 0], [0, 1]]]
)
def test_rotation_matrix_shape(R: list[list[float]]) -> None:
    with pytest.raises(ValidationError):
        Pose(t=[0, 0, 1], R=R)


@pytest.mark.parametrize("tz", [0.0, -1.0, -1e-9])
def test_target_must_be_in_front_of_the_camera(tz: float) -> None:
    with pytest.raises(ValidationError, match=r"t\[2\] must be > 0"):
        Pose(t=[0.0, 0.0, tz], q=[0.0, 0.0, 0.0])


def test_gibbs_vector_too_close_to_180_degrees_is_rejected() -> None:
    Pose(t=[0, 0, 1], q=[1e5, 0.0, 0.0])
    with pytest.raises(ValidationError, match="too large"):
        Pose(t=[0, 0, 1], q=[2e6, 0.0, 0.0])


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("field", ["t", "q", "quaternion", "R"])
def test_non_finite_numbers_are_rejected(field: str, bad: float) -> None:
    values: dict[str, Any] = {"t": [0.0, 0.0, 5.0], "q": [0.0, 0.0, 0.0]}
    if field == "t":
        values["t"] = [bad, 0.0, 5.0]
    elif field == "q":
        values["q"] = [0.0, bad, 0.0]
    elif field == "quaternion":
        values = {"t": [0.0, 0.0, 5.0], "quaternion": [1.0, 0.0, bad, 0.0]}
    else:
        R = [row[:] for row in ROT_Z_90]
        R[1][1] = bad
        values = {"t": [0.0, 0.0, 5.0], "R": R}
    with pytest.raises(ValidationError, match="finite"):
        Pose(**values)


def test_non_finite_json_is_rejected() -> None:
    with pytest.raises(ValidationError):
        Pose.model_validate_json('{"t": [0, 0, NaN], "q": [0, 0, 0]}')
    with pytest.raises(ValidationError):
        Pose.model_validate_json('{"t": [0, 0, 1e999], "q": [0, 0, 0]}')


# -- lighting -----------------------------------------------------------------------------
def test_sun_direction_must_be_unit_and_is_renormalised() -> None:
    v = [0.0, -0.6, -0.8005]  # norm 1.0004, within the 1e-3 tolerance
    lt = Lighting(sun_direction=v)
    assert math.sqrt(sum(c * c for c in lt.sun_direction)) == pytest.approx(1.0, abs=1e-15)
    for bad in ([0.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.0, -0.6, -0.81], [1.0, 1.0, 1.0]):
        with pytest.raises(ValidationError, match="unit vector"):
            Lighting(sun_direction=bad)
    with pytest.raises(ValidationError):
        Lighting(sun_direction=[0.0, 1.0])
    with pytest.raises(ValidationError):
        Lighting(sun_irradiance=0.0)
    with pytest.raises(ValidationError):
        Lighting(ambient=-0.1)
    with pytest.raises(ValidationError):
        Lighting(sun_direction=[math.nan, 0.0, 1.0])


# -- camera -------------------------------------------------------------------------------
def test_camera_defaults_and_a_valid_non_square_skewed_camera() -> None:
    assert Camera(**CAMERA).skew == 0.0
    Camera(**{**CAMERA, "fy": 420.0, "skew": 5.0, "cx": 170.0, "cy": 100.0})


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"width": 15}, "greater than or equal"),
        ({"height": 4097}, "less than or equal"),
        ({"fx": 0.0}, "greater than 0"),
        ({"fy": -400.0}, "greater than 0"),
        ({"fx": math.inf}, "finite"),
        ({"cx": math.nan}, "finite"),
        ({"cx": 700.0}, "implausibly far"),
        ({"cy": -300.0}, "implausibly far"),
        ({"fx": 10.0, "fy": 10.0}, "field of view"),
        ({"fx": 400.0 * 1000, "fy": 400.0 * 1000}, "field of view"),
        ({"fy": 900.0}, "aspect ratio"),
        ({"fx": 650.0}, "aspect ratio"),
        ({"skew": 100.0}, "skew"),
        ({"width": 320.5}, "integer"),
    ],
)
def test_camera_limits(change: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError) as exc:
        Camera(**{**CAMERA, **change})
    assert message in _errors(exc)


# -- extra=forbid -------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("model", "values"),
    [
        (Camera, {**CAMERA, "k1": 0.1}),
        (Pose, {"t": [0, 0, 1], "q": [0, 0, 0], "scale": 2}),
        (Lighting, {"sun_dir": [0, 0, 1]}),
        (EstimateOptions, {"max_iter": 3}),
        (
            EstimateRequest,
            {"camera": CAMERA, "initial_pose": {"t": [0, 0, 1], "q": [0, 0, 0]}, "model": "x"},
        ),
        (
            RenderRequest,
            {"camera": CAMERA, "pose": {"t": [0, 0, 1], "q": [0, 0, 0]}, "samples": 4},
        ),
    ],
)
def test_unknown_fields_are_rejected(model: type, values: dict[str, Any]) -> None:
    with pytest.raises(ValidationError) as exc:
        model.model_validate(values)  # type: ignore[attr-defined]
    assert "extra_forbidden" in _errors(exc)


def test_nested_unknown_field_is_rejected_with_its_location() -> None:
    body = {
        "camera": CAMERA,
        "initial_pose": {"t": [0, 0, 1], "q": [0, 0, 0]},
        "options": {"n_sample": 12},
    }
    with pytest.raises(ValidationError) as exc:
        EstimateRequest.model_validate(body)
    (err,) = exc.value.errors()
    assert err["type"] == "extra_forbidden" and err["loc"] == ("options", "n_sample")


def test_estimate_request_defaults() -> None:
    req = EstimateRequest.model_validate(
        {"camera": CAMERA, "initial_pose": {"t": [0, 0, 1], "q": [0, 0, 0]}}
    )
    assert req.lighting == Lighting()
    assert req.options == EstimateOptions()
    assert req.ground_truth is None


# -- options ------------------------------------------------------------------------------
def test_presets_name_only_real_fields() -> None:
    fields = set(EstimateOptions.model_fields)
    for method, preset in METHOD_PRESETS.items():
        assert set(preset) <= fields, method
        EstimateOptions.model_validate({**preset, "method": method})  # values are valid


def test_resolved_applies_the_preset_only_to_unset_fields() -> None:
    paper = EstimateOptions(method="paper", max_iterations=3, n_samples=30).resolved()
    assert paper.max_iterations == 3 and paper.n_samples == 30  # explicit wins
    assert paper.max_features == 4 and paper.coarse == "none"  # preset fills the rest
    assert paper.jacobian == "common" and paper.reuse_jacobian is False
    assert paper.spp == EstimateOptions().spp  # not in the preset: the field default
    # Setting a field to its default value still counts as set.
    explicit_default = EstimateOptions(method="paper", coarse="pnp").resolved()
    assert explicit_default.coarse == "pnp"
    pnp = EstimateOptions(method="pnp").resolved()
    assert pnp.coarse == "pnp" and pnp.refine_features == "none"
    assert EstimateOptions().resolved() == EstimateOptions()


def test_resolved_survives_a_json_round_trip() -> None:
    """The service stores requests as JSON: which fields were set must survive."""
    opts = EstimateOptions.model_validate_json('{"method": "paper", "max_features": 50}')
    assert opts.resolved().max_features == 50
    assert opts.resolved().n_samples == 24
    dumped = EstimateOptions.model_validate_json(opts.model_dump_json(exclude_unset=True))
    assert dumped.resolved() == opts.resolved()


@pytest.mark.parametrize(
    "change",
    [
        {"method": "magic"},
        {"max_iterations": 0},
        {"n_samples": 5},
        {"epsilon": 0.0},
        {"perturbation_scale": 0.1},
        {"ratio": 1.0},
        {"jacobian": "global"},
        {"spp": 0},
        {"seed": -1},
    ],
)
def test_option_limits(change: dict[str, Any]) -> None:
    with pytest.raises(ValidationError):
        EstimateOptions(**change)


def test_result_serialises_lambda_by_its_alias() -> None:
    pose = {"R": ROT_Z_90, "q": [0, 0, 0], "quaternion": [1, 0, 0, 0], "t": [0, 0, 1]}
    record = {
        "iteration": 1,
        "stage": "refine",
        "pose": pose,
        "cost": 1.0,
        "step_norm": 0.1,
        "lambda": 1e-3,
        "accepted": True,
        "features": 10,
        "renders": 13,
        "seconds": 0.5,
    }
    result = EstimateResult(
        pose=pose,
        initial_pose=pose,
        converged=True,
        reason="cost_converged",
        iterations=1,
        renders=13,
        seconds=0.5,
        method="default",
        history=[record],
        features=10,
        rms_residual_px=0.2,
        alignment_score=0.95,
        variant="scalar_rgb",
    )
    data = json.loads(result.model_dump_json())
    assert data["history"][0]["lambda"] == 1e-3 and "lambda_" not in data["history"][0]
    assert EstimateResult.model_validate_json(result.model_dump_json()) == result
