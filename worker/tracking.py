"""Tracking a sequence of image files: frames in, ``track.json``, a CSV and a trajectory plot
out (``proxpose track`` and the track job both run :func:`run_track`)."""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.settings import get_settings
from schemas.track import TrackFrame, TrackRequest, TrackResult, summarise
from worker.engine.exceptions import ImageSizeMismatchError, InvalidInputError
from worker.engine.images import decode_image
from worker.engine.posemath import pose_from_schema, pose_to_schema
from worker.entry import init_renderer_backend, load_target

#: Frame file types, by suffix (taken in name order).
FRAME_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")

FrameCallback = Callable[[TrackFrame], None]


@dataclass(frozen=True)
class FrameFile:
    name: str
    data: bytes


def frame_files(directory: Path) -> list[Path]:
    """The frames in ``directory``, in name order."""
    return sorted(
        (p for p in directory.iterdir() if p.suffix.lower() in FRAME_SUFFIXES and p.is_file()),
        key=lambda p: p.name,
    )


def check_frames(frames: Sequence[FrameFile], request: TrackRequest) -> None:
    """Raise InvalidInputError naming the first frame that cannot be used (unreadable, or not
    the camera's size), and when the truth does not give one pose per frame. Only headers are
    read, so a bad last frame is found before any work."""
    from PIL import Image, UnidentifiedImageError

    if not frames:
        raise InvalidInputError("no frames: the sequence is empty")
    cam = request.camera
    for frame in frames:
        try:
            with Image.open(io.BytesIO(frame.data)) as img:
                w, h = img.size
        except (UnidentifiedImageError, OSError) as exc:
            raise InvalidInputError(f"frame {frame.name}: not a readable image ({exc})") from exc
        if (w, h) != (cam.width, cam.height):
            raise ImageSizeMismatchError(
                f"frame {frame.name} is {w}×{h} px but the camera is {cam.width}×{cam.height} px"
            )
    truth = request.ground_truth
    if truth is not None and len(truth) != len(frames):
        raise InvalidInputError(
            f"ground_truth has {len(truth)} poses for {len(frames)} frames (need one per frame)"
        )


def run_track(
    model_path: str | Path,
    frames: Sequence[FrameFile],
    request: TrackRequest,
    on_frame: FrameCallback | None = None,
    should_cancel: Callable[[], bool] | None = None,
) -> TrackResult:
    """Track ``frames`` in order; ``on_frame`` is called with each frame's outcome."""
    import mitsuba as mi

    from worker.align.tracker import Tracker

    settings = get_settings()
    init_renderer_backend()
    check_frames(frames, request)
    model = load_target(model_path)
    tracker = Tracker(model, request.estimate_request(), should_cancel)
    truths = request.ground_truth
    out: list[TrackFrame] = []
    for k, frame in enumerate(frames):
        image = decode_image(frame.data, settings.max_image_pixels)
        truth = pose_from_schema(truths[k]) if truths is not None else None
        result = tracker.track(image, truth)
        tf = TrackFrame(
            image=frame.name,
            index=k,
            pose=pose_to_schema(result.R, result.t),
            converged=result.converged,
            status=result.status,  # type: ignore[arg-type]
            reason=result.reason,
            seconds=round(result.seconds, 4),
            renders=result.renders,
            render_cost=result.render_cost,
            alignment_score=round(result.alignment_score, 5),
            features=result.features,
            relearned=result.relearned,
            covariance=result.covariance,
            errors=result.errors,
        )
        out.append(tf)
        if on_frame is not None:
            on_frame(tf)
    return TrackResult(
        frames=out,
        summary=summarise(out),
        method=request.options.method,
        variant=str(mi.variant()),
    )


def track_csv(result: TrackResult) -> str:
    """One row per frame: status, pose (t, quaternion), errors."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(
        ["index", "image", "status", "converged", "seconds", "renders", "tx", "ty", "tz",
         "qw", "qx", "qy", "qz", "range", "rotation_error_deg", "translation_pct_of_range"]
    )  # fmt: skip
    for f in result.frames:
        t = f.pose.t
        q = f.pose.quaternion
        e = f.errors
        w.writerow(
            [f.index, f.image, f.status, int(f.converged), f.seconds, f.renders, *t, *q,
             round(float(np.linalg.norm(t)), 6),
             "" if e is None else round(e.rotation_deg, 6),
             "" if e is None else round(e.translation_pct_of_range, 6)]
        )  # fmt: skip
    return buf.getvalue()


def attitude_deg(result: TrackResult) -> np.ndarray:
    """Each frame's attitude as rotation-vector components relative to the first frame (deg)."""
    from worker.engine.posemath import matrix_to_rotvec

    Rs = [np.asarray(f.pose.R) for f in result.frames]
    return np.array([np.degrees(matrix_to_rotvec(Rs[0].T @ R)) for R in Rs]).reshape(-1, 3)


def trajectory_png(result: TrackResult) -> bytes:
    """Range, attitude (relative to the first frame) and, with a truth, the per-frame errors;
    markers show each frame's status."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = np.array([f.index for f in result.frames])
    rng = np.array([float(np.linalg.norm(f.pose.t)) for f in result.frames])
    att = attitude_deg(result)
    has_truth = any(f.errors is not None for f in result.frames)
    rows = 3 if has_truth else 2
    fig, axes = plt.subplots(rows, 1, figsize=(7, 2.2 * rows), sharex=True)
    axes[0].plot(k, rng, "-", color="0.3")
    axes[0].set_ylabel("range")
    for i, name in enumerate("xyz"):
        axes[1].plot(k, att[:, i], label=f"θ{name}")
    axes[1].set_ylabel("attitude (°)")
    axes[1].legend(fontsize=7, ncol=3)
    colours = {"tracked": "tab:green", "reinitialised": "tab:orange", "lost": "tab:red"}
    for status, colour in colours.items():
        sel = np.array([f.status == status for f in result.frames])
        if sel.any():
            axes[0].scatter(k[sel], rng[sel], s=14, color=colour, label=status, zorder=3)
    axes[0].legend(fontsize=7, ncol=3)
    if has_truth:
        rot = [f.errors.rotation_deg if f.errors else np.nan for f in result.frames]
        tr = [f.errors.translation_pct_of_range if f.errors else np.nan for f in result.frames]
        axes[2].semilogy(k, rot, "o-", ms=3, label="rotation (°)")
        axes[2].semilogy(k, tr, "s-", ms=3, label="translation (% of range)")
        axes[2].set_ylabel("error")
        axes[2].legend(fontsize=7)
    axes[-1].set_xlabel("frame")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()
