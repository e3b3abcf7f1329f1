"""``proxpose bench --sequences``: the tracker against chained single estimates, paired.

Each sequence (:mod:`worker.bench.sequences`: an approach, a fly-around, a fast tumble with a
jump the tracker cannot follow) is rendered once with a reference class's physics; then the
tracker runs through it, and so do chained full estimates (each frame's estimate starting from
the previous frame's result, as a user chaining ``proxpose estimate`` would), on the same
frames in the same process. Reported per sequence and method: engine seconds per frame
(median over tracked frames for the tracker), frames per second, renders, per-frame rotation
and translation errors (median, max), re-initialisations and lost frames, and whether the
frame after a jump was caught (re-initialised, or a tracked frame that learned its rows afresh:
one whose LM was still moving after its iterations goes on from fresh rows before a full
estimate) and followed within the accuracy bound.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from schemas.pose import Pose
from schemas.track import TrackFrame, summarise
from worker.bench.records import sigma_length
from worker.bench.sequences import MOTIONS, Sequence, make_sequence
from worker.engine.exceptions import ProxposeError

#: Default sequences: motions, frames each, reference classes.
DEFAULT_MOTIONS = ("approach", "flyaround", "tumble")
DEFAULT_FRAMES = 24
DEFAULT_REFERENCES = ("combined", "rough")
#: A frame within this of the truth counts as accurate (the hidden sequence's bound).
ACCURATE_DEG = 0.3
ACCURATE_PCT = 0.3


@dataclass
class SequenceRun:
    model: str
    motion: str
    reference: str
    method: str  # track | chained
    frames: list[TrackFrame]

    def row(self, jump_at: int | None) -> dict[str, Any]:
        s = summarise(self.frames)
        tracked = [f.seconds for f in self.frames if f.status == "tracked"]
        tracked_cost = [f.render_cost for f in self.frames if f.status == "tracked"]
        per_frame = [f.seconds for f in self.frames[1:]] or [f.seconds for f in self.frames]
        rot = [f.errors.rotation_deg for f in self.frames if f.errors]
        tr = [f.errors.translation_pct_of_range for f in self.frames if f.errors]
        jump = None
        if jump_at is not None and jump_at < len(self.frames):
            f = self.frames[jump_at]
            e = f.errors
            followed = e is not None and e.rotation_deg < ACCURATE_DEG
            relearned = f.status == "tracked" and f.relearned
            jump = {
                "status": f"{f.status}, learned afresh" if relearned else f.status,
                "caught": f.status == "reinitialised" or relearned,
                "recovered": followed,
            }
        return {
            "model": self.model,
            "motion": self.motion,
            "reference": self.reference,
            "method": self.method,
            "frames": s.frames,
            "tracked": s.tracked,
            "reinitialised": s.reinitialised,
            "lost": s.lost,
            "converged": s.converged,
            "median_s_per_frame": float(np.median(per_frame)),
            "median_s_per_tracked_frame": float(np.median(tracked)) if tracked else None,
            "frames_per_second": s.frames_per_second,
            "renders_per_frame": s.renders / max(s.frames, 1),
            "render_cost_per_frame": s.render_cost / max(s.frames, 1),
            "render_cost_per_tracked_frame": float(np.mean(tracked_cost)) if tracked_cost else None,
            "rot_median_deg": float(np.median(rot)) if rot else None,
            "rot_max_deg": float(np.max(rot)) if rot else None,
            "trans_median_pct": float(np.median(tr)) if tr else None,
            "trans_max_pct": float(np.max(tr)) if tr else None,
            "accurate": sum(
                1
                for f in self.frames
                if f.errors
                and f.errors.rotation_deg < ACCURATE_DEG
                and f.errors.translation_pct_of_range < ACCURATE_PCT
            ),
            "jump": jump,
            "per_frame": [_frame_detail(f) for f in self.frames],
        }


def _frame_detail(f: TrackFrame) -> dict[str, Any]:
    """What traces a sequence's maximum to its frame: status, stop rule, renders, whether
    the Jacobian was learned again, the errors and the reported 1-σ rotation."""
    e, c = f.errors, f.covariance
    return {
        "status": f.status,
        "reason": f.reason,
        "renders": f.renders,
        "relearned": f.relearned,
        "seconds": round(f.seconds, 3),
        "rot_deg": round(e.rotation_deg, 4) if e else None,
        "trans_pct": round(e.translation_pct_of_range, 4) if e else None,
        "sigma_rot_deg": round(sigma_length(c.sigma_rotation_deg), 4) if c else None,
    }


def run_tracker(model: Any, seq: Sequence) -> list[TrackFrame]:
    """The tracker through ``seq``."""
    from worker.align.tracker import Tracker

    tracker = Tracker(model, seq.request)
    out = []
    for k, (frame, truth) in enumerate(zip(seq.frames, seq.truths, strict=True)):
        result = tracker.track(_float(frame), truth)
        out.append(_frame(k, result))
    return out


def run_chained(model: Any, seq: Sequence) -> list[TrackFrame]:
    """A full estimate per frame, each from the previous frame's result; a frame whose estimate
    fails (e.g. too few features) is 'lost', its pose the start, and the next frame starts
    from there too."""
    from worker.align.estimator import estimate
    from worker.bench.synth import pose_json

    request = seq.request
    out = []
    for k, (frame, truth) in enumerate(zip(seq.frames, seq.truths, strict=True)):
        start = time.perf_counter()
        req = request.model_copy(update={"ground_truth": pose_json(*truth)})
        try:
            est = estimate(model, _float(frame), req)
        except ProxposeError as exc:
            out.append(_failed(k, request.initial_pose, truth, time.perf_counter() - start, exc))
            continue
        r = est.result
        out.append(
            TrackFrame(
                image=f"frame_{k:03d}",
                index=k,
                pose=r.pose,
                converged=r.converged,
                status="reinitialised",
                reason=r.reason,
                seconds=round(time.perf_counter() - start, 4),
                renders=r.renders,
                render_cost=r.render_cost,
                alignment_score=r.alignment_score,
                features=r.features,
                covariance=r.covariance,
                errors=r.errors,
            )
        )
        request = request.model_copy(
            update={"initial_pose": Pose(t=r.pose.t, quaternion=r.pose.quaternion)}
        )
    return out


def _failed(k: int, start: Pose, truth: Any, seconds: float, exc: ProxposeError) -> TrackFrame:
    """A chained frame whose full estimate failed: lost, at its start pose."""
    from worker.align.estimator import errors_between
    from worker.engine.posemath import pose_from_schema, pose_to_schema

    R, t = pose_from_schema(start)
    return TrackFrame(
        image=f"frame_{k:03d}",
        index=k,
        pose=pose_to_schema(R, t),
        converged=False,
        status="lost",
        reason=exc.code,
        seconds=round(seconds, 4),
        renders=0,
        render_cost=0.0,
        alignment_score=-1.0,
        features=0,
        errors=errors_between(truth, R, t),
    )


def _float(frame: np.ndarray) -> np.ndarray:
    """A rendered 8-bit frame as decode_image gives a PNG of it."""
    return frame.astype(np.float32) / 255.0


def _frame(k: int, result: Any) -> TrackFrame:
    from worker.engine.posemath import pose_to_schema

    return TrackFrame(
        image=f"frame_{k:03d}",
        index=k,
        pose=pose_to_schema(result.R, result.t),
        converged=result.converged,
        status=result.status,
        reason=result.reason,
        seconds=round(result.seconds, 4),
        renders=result.renders,
        render_cost=result.render_cost,
        alignment_score=result.alignment_score,
        features=result.features,
        relearned=result.relearned,
        covariance=result.covariance,
        errors=result.errors,
    )


def run_suite(
    models: list[tuple[str, Path]],
    motions: list[str],
    references: list[str],
    n_frames: int,
    sizes: list[tuple[int, int]],
    seed: int,
    output: Path,
    chained: bool = True,
) -> list[dict[str, Any]]:
    """Every (size, model, motion, reference) sequence through the tracker (and chained
    estimates); writes OUTPUT/sequences.json and sequences.md and returns the rows. A size
    W×H that is not square has its principal point off the centre (bench_camera); the
    sequences of one (model, motion, reference) show the same motion at every size."""
    from worker.bench.cases import bench_camera
    from worker.engine.meshes import load_model

    rows: list[dict[str, Any]] = []
    output.mkdir(parents=True, exist_ok=True)
    methods = [("track", run_tracker)] + ([("chained", run_chained)] if chained else [])
    for w, h in sizes:
        camera = bench_camera(w, None if w == h else h)
        for mi_, (name, path) in enumerate(models):
            model = load_model(path)
            for mo, motion in enumerate(motions):
                for ri, reference in enumerate(references):
                    seq_seed = seed * 1000 + 100 * mi_ + 10 * mo + ri
                    seq = make_sequence(
                        model, camera, MOTIONS[motion], n_frames, seq_seed, reference
                    )
                    jump_at = MOTIONS[motion].jump_at
                    for method, runner in methods:
                        frames = runner(model, seq)
                        run = SequenceRun(name, motion, reference, method, frames)
                        row = {"size": f"{w}x{h}", **run.row(jump_at)}
                        rows.append(row)
                        print(_line(row), flush=True)
                        _write(output, rows)
    return rows


def _line(r: dict[str, Any]) -> str:
    spf = r["median_s_per_tracked_frame"] or r["median_s_per_frame"]
    return (
        f"{r['size']} {r['model']} {r['motion']} {r['reference']} {r['method']}: "
        f"{r['converged']}/{r['frames']} converged, {r['tracked']} tracked, "
        f"{r['reinitialised']} re-init, {r['lost']} lost; median {spf:.3f} s/frame, "
        f"rot median {r['rot_median_deg']:.4f}° max {r['rot_max_deg']:.4f}°, "
        f"transl. median {r['trans_median_pct']:.4f} % max {r['trans_max_pct']:.4f} %"
        + (f"; jump: {r['jump']['status']}" if r["jump"] else "")
    )


def _write(output: Path, rows: list[dict[str, Any]]) -> None:
    (output / "sequences.json").write_text(json.dumps(rows, indent=1))
    head = (
        "| size | model | motion | reference | method | converged | tracked / re-init / lost | "
        "s per frame (median) | renders per frame | rot. median / max | "
        "transl. median / max | jump frame |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        spf = r["median_s_per_tracked_frame"] or r["median_s_per_frame"]
        jump = r["jump"]["status"] if r["jump"] else ""
        lines.append(
            f"| {r['size']} | {r['model']} | {r['motion']} | {r['reference']} | {r['method']} | "
            f"{r['converged']}/{r['frames']} | {r['tracked']} / {r['reinitialised']} / "
            f"{r['lost']} | {spf:.3f} s | {r['renders_per_frame']:.1f} | "
            f"{r['rot_median_deg']:.4f}° / {r['rot_max_deg']:.4f}° | "
            f"{r['trans_median_pct']:.4f} % / {r['trans_max_pct']:.4f} % | {jump} |"
        )
    (output / "sequences.md").write_text(head + "\n".join(lines) + "\n")
