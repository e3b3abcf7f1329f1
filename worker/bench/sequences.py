"""Image sequences for the tracking suite: an approach, a fly-around and a fast tumble.

The truth moves smoothly (a fixed body rotation per frame, the range closing, or the camera
circling the target); a tumble also jumps once, by more than a tracker can follow, so that
the frame is lost and must be recovered. Each frame is rendered by a reference class of
:mod:`worker.bench.references` (other physics than the estimator's), the sun fixed in the
camera's frame (an inertially pointed chaser; a request carries one lighting), and the first
frame's initial guess is a few degrees and percent off.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas.camera import Camera
from schemas.estimate import EstimateRequest
from schemas.lighting import Lighting
from worker.bench.references import REFERENCE_CLASSES, render_class_reference
from worker.bench.synth import CaseSpec, draw_sun, draw_truth, perturb_direction, pose_json
from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel
from worker.engine.posemath import axis_angle_to_matrix

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Motion:
    """How the truth moves from frame to frame."""

    name: str
    spin_deg: float  # body rotation per frame
    closing: float  # fraction of the range gained over the sequence
    orbit_deg: float = 0.0  # the camera's circling of the target per frame
    jump_at: int | None = None  # frame at which the attitude jumps by jump_deg
    jump_deg: float = 0.0


MOTIONS = {
    "approach": Motion("approach", spin_deg=0.8, closing=0.25),
    "flyaround": Motion("flyaround", spin_deg=0.2, closing=0.0, orbit_deg=1.5),
    "tumble": Motion("tumble", spin_deg=2.0, closing=0.05, jump_at=12, jump_deg=12.0),
}


@dataclass
class Sequence:
    frames: list[NDArray[np.uint8]]
    truths: list[tuple[Array, Array]]
    request: EstimateRequest  # initial_pose: the first frame's guess; ground_truth: none


def truths(
    model: LoadedModel,
    camera: PinholeCamera,
    motion: Motion,
    n: int,
    rng: np.random.Generator,
    fill: float = 0.5,
) -> list[tuple[Array, Array]]:
    """The true poses of ``n`` frames, the first filling ``fill`` of the image."""
    R, t = draw_truth(model, camera, CaseSpec(0.0, 0.0, fill=fill), rng)
    axis = rng.normal(size=3)
    step = axis_angle_to_matrix(axis, np.radians(motion.spin_deg))
    orbit = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.radians(motion.orbit_deg))
    centre = R @ model.centre + t
    out = []
    for k in range(n):
        scale = 1.0 - motion.closing * k / max(n - 1, 1)
        out.append((R, centre * scale - R @ model.centre))
        R = R @ step
        if motion.jump_at is not None and k + 1 == motion.jump_at:
            R = R @ axis_angle_to_matrix(rng.normal(size=3), np.radians(motion.jump_deg))
        if motion.orbit_deg:
            # The camera circles the target, pointed at it: in the camera's frame the target
            # turns about its own centre, which stays where it is in the image (turning the
            # scene about the camera instead panned the target out of the frame in ~15 frames).
            R = orbit @ R
    return out


def make_sequence(
    model: LoadedModel,
    camera: Camera,
    motion: Motion,
    n: int,
    seed: int,
    reference: str = "combined",
    offset_deg: float = 2.0,
    fill: float = 0.5,
) -> Sequence:
    """``n`` frames of ``motion`` rendered as class ``reference``, and the request."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera.from_schema(camera)
    poses = truths(model, cam, motion, n, rng, fill)
    sun = draw_sun(rng)  # fixed in the camera's frame
    cls = REFERENCE_CLASSES[reference]
    sun_true = perturb_direction(sun, cls.sun_error_deg, rng)
    frames = [render_class_reference(model, cam, R, t, sun_true, cls, rng) for R, t in poses]
    R0, t0 = poses[0]
    guess_R = R0 @ axis_angle_to_matrix(rng.normal(size=3), np.radians(offset_deg))
    guess_t = t0 + rng.normal(size=3) / np.sqrt(3) * 0.02 * float(np.linalg.norm(t0))
    request = EstimateRequest(
        camera=camera,
        initial_pose=pose_json(guess_R, guess_t),
        lighting=Lighting(sun_direction=list(map(float, sun))),
    )
    return Sequence(frames, poses, request)


def write_sequence(seq: Sequence, directory: Path) -> Path:
    """Write the frames (frame_000.png, …) and request.json, with the truth per frame, into
    ``directory``: the input of ``proxpose track``. Returns the request's path."""
    import cv2

    from schemas.track import TrackRequest

    directory.mkdir(parents=True, exist_ok=True)
    for k, frame in enumerate(seq.frames):
        rgb = frame if frame.ndim == 2 else frame[..., ::-1]
        cv2.imwrite(str(directory / f"frame_{k:03d}.png"), rgb)
    request = TrackRequest(
        camera=seq.request.camera,
        initial_pose=seq.request.initial_pose,
        lighting=seq.request.lighting,
        options=seq.request.options,
        ground_truth=[pose_json(R, t) for R, t in seq.truths],
    )
    path = directory / "request.json"
    path.write_text(request.model_dump_json(indent=1, exclude_defaults=True))
    return path
