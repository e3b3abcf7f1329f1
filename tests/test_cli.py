"""The ``proxpose`` command line, run as a subprocess: the estimate and render contracts, and
one-line errors for bad input."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from worker.engine.images import decode_image

REPO = Path(__file__).resolve().parents[1]
PROXPOSE = shutil.which("proxpose", path=str(Path(sys.executable).parent)) or "proxpose"
ARTIFACTS = {"overlay_1", "overlay_2", "overlay_final", "difference", "final_render", "convergence"}
#: A non-square image, so that a width/height swap shows.
CAMERA = {"width": 192, "height": 144, "fx": 230.0, "fy": 230.0, "cx": 95.5, "cy": 71.5}


def run_cli(*args: str | Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "PROXPOSE_DATA_DIR"}
    return subprocess.run(
        [PROXPOSE, *map(str, args)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _pose_json(R: np.ndarray, t: np.ndarray) -> dict[str, Any]:
    from worker.engine.posemath import matrix_to_quaternion

    return {"t": t.tolist(), "quaternion": matrix_to_quaternion(R).tolist()}


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory: pytest.TempPathFactory, variant: str) -> Path:
    """The demo satellite, a reference image and REQUEST.json / POSE.json written as a user
    would (initial guess 3° and 3 % off the truth, which is given as ground_truth)."""
    from schemas.camera import Camera
    from worker.bench.synth import CaseSpec, make_case
    from worker.demo.satellite import demo_satellite_path
    from worker.engine.meshes import load_model

    d = tmp_path_factory.mktemp("cli")
    model_path = demo_satellite_path(d)
    shutil.copy(model_path, d / "sat.glb")
    case = make_case(
        load_model(model_path), Camera(**CAMERA), CaseSpec(3.0, 0.03, fill=0.9), seed=1
    )
    Image.fromarray(case.reference).save(d / "ref.png")
    req = case.request
    request = {
        "camera": CAMERA,
        "initial_pose": req.initial_pose.model_dump(exclude_none=True),
        "lighting": {"sun_direction": req.lighting.sun_direction},
        "ground_truth": _pose_json(case.R_true, case.t_true),
    }
    (d / "request.json").write_text(json.dumps(request, indent=2))
    (d / "pose.json").write_text(json.dumps(_pose_json(case.R_true, case.t_true)))
    return d


def _assert_one_line_error(proc: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: "), lines[0]
    assert "Traceback" not in proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.mark.slow
def test_estimate_writes_result_and_artifacts(case_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = run_cli(
        "estimate",
        "--model", case_dir / "sat.glb",
        "--image", case_dir / "ref.png",
        "--request", case_dir / "request.json",
        "--output", out,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "result.json" in proc.stdout
    result = json.loads((out / "result.json").read_text())
    pose = result["pose"]
    assert set(pose) == {"R", "q", "quaternion", "t"}
    R = np.array(pose["R"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert len(pose["q"]) == 3 and len(pose["quaternion"]) == 4 and len(pose["t"]) == 3
    assert isinstance(result["converged"], bool) and result["reason"]
    assert result["iterations"] == len(result["history"]) > 0
    assert result["renders"] >= result["iterations"]
    assert {"iteration", "stage", "cost", "lambda", "accepted", "features"} <= set(
        result["history"][0]
    )
    cov = result["covariance"]
    assert np.array(cov["matrix"]).shape == (6, 6)
    assert len(cov["sigma_rotation_deg"]) == 3 and len(cov["sigma_translation"]) == 3
    assert result["errors"]["rotation_deg"] < result["initial_errors"]["rotation_deg"]
    assert set(result["artifacts"]) == ARTIFACTS
    assert {p.name for p in out.iterdir()} == {"result.json"} | {f"{a}.png" for a in ARTIFACTS}
    for name in ARTIFACTS - {"convergence"}:  # image-sized artifacts
        img = decode_image((out / f"{name}.png").read_bytes())
        assert img.shape[:2] == (CAMERA["height"], CAMERA["width"]), name


@pytest.mark.slow
def test_render_writes_a_png_of_the_camera_size(case_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "sub" / "render.png"
    proc = run_cli(
        "render",
        "--model", case_dir / "sat.glb",
        "--request", case_dir / "request.json",
        "--pose", case_dir / "pose.json",
        "--output", out,
        "--spp", "8",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    img = decode_image(out.read_bytes())
    assert img.shape == (CAMERA["height"], CAMERA["width"], 3)
    # The render at the true pose shows the target where the reference does.
    ref = decode_image((case_dir / "ref.png").read_bytes())
    lit_render, lit_ref = img.mean(axis=2) > 0.05, ref.mean(axis=2) > 0.15
    overlap = (lit_render & lit_ref).sum() / lit_ref.sum()
    assert lit_render.mean() > 0.02 and overlap > 0.8


# -- bad input ----------------------------------------------------------------------------
def _request(case_dir: Path, **changes: Any) -> dict[str, Any]:
    request = json.loads((case_dir / "request.json").read_text())
    request.update(changes)
    return request


def _estimate(case_dir: Path, tmp_path: Path, body: Any = None, **paths: Path | str) -> Any:
    """``proxpose estimate`` on the case, with REQUEST.json replaced by ``body`` if given."""
    if body is not None:
        (tmp_path / "req.json").write_text(body if isinstance(body, str) else json.dumps(body))
    args = {
        "model": case_dir / "sat.glb",
        "image": case_dir / "ref.png",
        "request": tmp_path / "req.json" if body is not None else case_dir / "request.json",
        "output": tmp_path / "out",
        **paths,
    }
    return run_cli("estimate", *[x for k, v in args.items() for x in (f"--{k}", v)])


@pytest.mark.parametrize("which", ["model", "image", "request"])
def test_missing_files(case_dir: Path, tmp_path: Path, which: str) -> None:
    proc = _estimate(case_dir, tmp_path, **{which: tmp_path / "missing.bin"})
    _assert_one_line_error(proc, "missing.bin")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("request_body", "needle"),
    [
        ('{"camera": {"width": 192,', "request"),  # malformed JSON
        ("[]", "request"),
        (None, "focal_length: Extra inputs are not permitted"),  # an unknown field
        ("t_behind", "t[2] must be > 0"),
        ("sun", "unit vector"),
        ("two_attitudes", "exactly one of"),
    ],
    ids=["malformed", "not-an-object", "unknown-field", "t-behind", "non-unit-sun", "attitudes"],
)
def test_invalid_requests(
    case_dir: Path, tmp_path: Path, request_body: str | None, needle: str
) -> None:
    body: Any
    if request_body is None:
        body = _request(case_dir, focal_length=3.0)
    elif request_body == "t_behind":
        body = _request(case_dir, initial_pose={"t": [0.0, 0.0, -30.0], "q": [0.0, 0.0, 0.0]})
    elif request_body == "sun":
        body = _request(case_dir, lighting={"sun_direction": [0.0, 1.0, 1.0]})
    elif request_body == "two_attitudes":
        body = _request(
            case_dir,
            initial_pose={"t": [0.0, 0.0, 30.0], "q": [0.0, 0.0, 0.0], "quaternion": [1, 0, 0, 0]},
        )
    else:
        body = request_body
    proc = _estimate(case_dir, tmp_path, body=body)
    _assert_one_line_error(proc, needle)
    assert proc.returncode == 2


def test_image_of_the_wrong_size(case_dir: Path, tmp_path: Path) -> None:
    small = tmp_path / "small.png"
    Image.new("RGB", (CAMERA["width"], CAMERA["height"] + 1)).save(small)
    proc = _estimate(case_dir, tmp_path, image=small)
    _assert_one_line_error(proc, "192×145", "image_size_mismatch")
    assert proc.returncode == 2


def test_file_that_is_not_an_image(case_dir: Path, tmp_path: Path) -> None:
    fake = tmp_path / "ref.png"
    fake.write_text("definitely not a PNG")
    proc = _estimate(case_dir, tmp_path, image=fake)
    _assert_one_line_error(proc, "invalid_image")
    assert proc.returncode == 2


def test_model_that_is_not_a_mesh(case_dir: Path, tmp_path: Path) -> None:
    fake = tmp_path / "sat.glb"
    fake.write_bytes(b"glTF but not really")
    proc = _estimate(case_dir, tmp_path, model=fake)
    _assert_one_line_error(proc, "invalid_model")
    assert proc.returncode == 2


@pytest.mark.slow
def test_target_out_of_view_fails_the_estimate(case_dir: Path, tmp_path: Path) -> None:
    """Valid input, but nothing to see at the initial guess: the estimate fails (status 1)."""
    body = _request(case_dir, initial_pose={"t": [500.0, 0.0, 30.0], "q": [0.0, 0.0, 0.0]})
    proc = _estimate(case_dir, tmp_path, body=body)
    _assert_one_line_error(proc, "empty_render")
    assert proc.returncode == 1


def test_render_rejects_a_pose_behind_the_camera(case_dir: Path, tmp_path: Path) -> None:
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"t": [0.0, 0.0, -5.0], "quaternion": [1.0, 0.0, 0.0, 0.0]}))
    proc = run_cli(
        "render",
        "--model", case_dir / "sat.glb",
        "--request", case_dir / "request.json",
        "--pose", pose,
        "--output", tmp_path / "r.png",
    )  # fmt: skip
    _assert_one_line_error(proc, "pose.json", "t[2] must be > 0")
    assert not (tmp_path / "r.png").exists()


def test_usage_errors_exit_2_without_traceback() -> None:
    proc = run_cli("estimate", "--model", "x.glb")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "required" in proc.stderr
