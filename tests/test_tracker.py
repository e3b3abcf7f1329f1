"""Tracking a sequence (``proxpose track``): the CLI contract on a short sequence of real
renders with another renderer's physics, a forced loss that must be recovered, and one-line
errors for bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from schemas.track import TrackResult
from tests.test_cli import _assert_one_line_error, run_cli
from worker.engine.meshes import LoadedModel

CAMERA = {"width": 192, "height": 144, "fx": 230.0, "fy": 230.0, "cx": 95.5, "cy": 71.5}
N_FRAMES = 7
#: The frame that shows nothing (a sensor dropout): the loss the tracker must detect.
DROPOUT = 3


def recorded_estimates(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The full estimates the tracker runs (the real ones), recorded in order."""
    import worker.align.tracker as tracker_module

    estimates: list[Any] = []
    real = tracker_module.estimate

    def recorded(*args: Any, **kwargs: Any) -> Any:
        estimates.append(real(*args, **kwargs))
        return estimates[-1]

    monkeypatch.setattr(tracker_module, "estimate", recorded)
    return estimates


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory: pytest.TempPathFactory, variant: str) -> Path:
    """The demo satellite spinning 1°/frame and closing 10 %, rendered by the bench's ray
    tracer with another tone curve (not the estimator's physics), frame DROPOUT black; the
    first guess 2° and 2 % off; the truth per frame in request.json."""
    from schemas.camera import Camera
    from worker.bench.sequences import Motion, make_sequence, write_sequence
    from worker.demo.satellite import demo_satellite_path
    from worker.engine.meshes import load_model

    d = tmp_path_factory.mktemp("track")
    model_path = demo_satellite_path(d)
    shutil.copy(model_path, d / "sat.glb")
    motion = Motion("test", spin_deg=1.0, closing=0.1)
    model = load_model(model_path)
    seq = make_sequence(model, Camera(**CAMERA), motion, N_FRAMES, 3, "tone", fill=0.9)
    seq.frames[DROPOUT] = np.zeros_like(seq.frames[DROPOUT])
    write_sequence(seq, d / "frames")
    shutil.move(d / "frames" / "request.json", d / "request.json")
    return d


@pytest.mark.slow
def test_track_writes_frames_in_order_and_recovers_from_a_lost_frame(
    sequence_dir: Path, tmp_path: Path
) -> None:
    d = sequence_dir
    out = tmp_path / "out"
    proc = run_cli(
        "track", "--model", d / "sat.glb", "--images", d / "frames", "--request",
        d / "request.json", "--output", out, timeout=900,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    result = TrackResult.model_validate_json((out / "track.json").read_text())
    names = [f.image for f in result.frames]
    assert names == [f"frame_{k:03d}.png" for k in range(N_FRAMES)]
    assert [f.index for f in result.frames] == list(range(N_FRAMES))
    status = [f.status for f in result.frames]
    assert status[0] == "reinitialised"  # the first frame is a full estimate
    # The second starts a whole frame behind (no velocity yet): when its LM is still moving
    # after the frame's iterations it learns afresh and goes on, and is re-initialised when
    # that does not converge either.
    assert status[1] in ("tracked", "reinitialised"), status
    assert all(s == "tracked" for s in status[2:DROPOUT]), status
    assert status[DROPOUT] == "lost", status  # nothing to see: detected, the prediction stands
    assert all(s in ("tracked", "reinitialised") for s in status[DROPOUT + 1 :]), status
    for f in result.frames:
        if f.index == DROPOUT:
            assert not f.converged
            continue
        assert f.converged, status
        assert f.errors is not None and f.covariance is not None
        # At 192 × 144 the frames after the dropout end up to 0.7-0.85° off with the engines
        # of 6c46e2b and c188483 alike (sequence seeds 3-6, four each): what is checked here is
        # that the track recovers; its accuracy is the bench's (`proxpose bench --sequences`).
        assert f.errors.rotation_deg < 1.0, (f.index, f.errors)
        assert f.errors.translation_pct_of_range < 1.0, (f.index, f.errors)
    tracked = [f for f in result.frames if f.status == "tracked"]
    # A tracked frame costs a few renders, not a full estimate's; one that learns its
    # Jacobian again (perturbation renders at TRACK_PERTURBATION_SPP: on this short sequence
    # most tracked frames do) costs less than one.
    full = result.frames[0].render_cost
    kept = [f.render_cost for f in tracked if not f.relearned]
    assert kept and np.median(kept) < 0.3 * full
    assert all(f.render_cost < full for f in tracked if f.relearned)
    s = result.summary
    assert (s.frames, s.lost) == (N_FRAMES, 1)
    assert s.tracked + s.reinitialised == N_FRAMES - 1
    assert s.converged == N_FRAMES - 1
    rows = (out / "track.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + N_FRAMES and rows[0].startswith("index,image,status")
    png = Image.open(out / "trajectory.png")
    assert png.size[0] > 300 and png.size[1] > 300
    assert f"{N_FRAMES} frames: {s.tracked} tracked, {s.reinitialised} re-initialised, 1 lost" in (
        proc.stdout
    )


def test_a_frame_of_the_wrong_size_is_named(sequence_dir: Path, tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    shutil.copytree(sequence_dir / "frames", frames)
    Image.fromarray(np.zeros((100, 120, 3), np.uint8)).save(frames / "frame_003.png")
    proc = run_cli(
        "track", "--model", sequence_dir / "sat.glb", "--images", frames, "--request",
        sequence_dir / "request.json", "--output", tmp_path / "out",
    )  # fmt: skip
    assert proc.returncode == 2
    _assert_one_line_error(proc, "frame_003.png", "120×100", "192×144")
    assert not (tmp_path / "out").exists()


def test_a_truth_that_is_not_one_pose_per_frame(sequence_dir: Path, tmp_path: Path) -> None:
    body = json.loads((sequence_dir / "request.json").read_text())
    body["ground_truth"] = body["ground_truth"][:-1]
    (tmp_path / "request.json").write_text(json.dumps(body))
    proc = run_cli(
        "track", "--model", sequence_dir / "sat.glb", "--images", sequence_dir / "frames",
        "--request", tmp_path / "request.json", "--output", tmp_path / "out",
    )  # fmt: skip
    assert proc.returncode == 2
    _assert_one_line_error(proc, "ground_truth", f"{N_FRAMES - 1} poses for {N_FRAMES} frames")


@pytest.mark.parametrize("case", ["empty", "not-an-image", "bad-request"])
def test_bad_input_exits_2_with_one_line(sequence_dir: Path, tmp_path: Path, case: str) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    request = sequence_dir / "request.json"
    needle = "no PNG, JPEG or TIFF frames"
    if case == "not-an-image":
        shutil.copy(sequence_dir / "frames" / "frame_000.png", frames / "a.png")
        (frames / "b.png").write_bytes(b"not a png")
        needle = "frame b.png: not a readable image"
    elif case == "bad-request":
        shutil.copy(sequence_dir / "frames" / "frame_000.png", frames / "a.png")
        body = json.loads(request.read_text())
        body["camera"]["width"] = -1
        request = tmp_path / "request.json"
        request.write_text(json.dumps(body))
        needle = "camera.width"
    proc = run_cli(
        "track", "--model", sequence_dir / "sat.glb", "--images", frames, "--request",
        request, "--output", tmp_path / "out",
    )  # fmt: skip
    assert proc.returncode == 2
    _assert_one_line_error(proc, needle)


@pytest.mark.slow
def test_a_frame_that_learns_its_jacobian_again_solves_for_the_sun_again(
    demo_model: LoadedModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tracked frames keep the sun the last fit left; a frame that learns its Jacobian again
    (here: the target turned RELEARN_ROTATION_DEG) solves for the sun's tilt again, its prior the
    request's sun. The request's sun is 4° off here (the bench's `sun` class).

    The target turns 2° a frame and the threshold is lowered to 3°, so that of two frames
    tracked after rows were learned the first keeps them and the second learns again: on this
    small target some frames are lost and re-initialised (which learns afresh), and which ones
    depends on the CPU (at 3.5° a frame and 6°, on an AMD EPYC VM frames 1 and 3 were, and no
    frame had turned 6° since its rows were learned)."""
    import worker.align.tracker as tracker_module
    from schemas.camera import Camera
    from worker.align.session import Session
    from worker.align.tracker import Tracker
    from worker.bench.sequences import Motion, make_sequence

    monkeypatch.setattr("worker.align.tracker.RELEARN_ROTATION_DEG", 3.0)
    # Only the turn relearns here: at 2° a frame on this small target every tracked frame
    # rejects a trial (one at the noise floor), and a rejected trial relearns too (that rule:
    # tests/test_tracker_frames.py), which would leave no frame that keeps its rows and sun.
    monkeypatch.setattr("worker.align.tracker.mispredicted", lambda session: False)
    # Whether each sun fit a relearning runs takes a step (the real stage, observed): a frame
    # whose rows were learned where the fit already sits rejects both trials and keeps the sun.
    sun_steps: list[bool] = []
    real_stage = tracker_module.run_lm_stage

    def observed(session: Session, *args: Any, fit_sun: bool = False, **kwargs: Any) -> str:
        before = len(session.history)
        out = real_stage(session, *args, fit_sun=fit_sun, **kwargs)
        if fit_sun:
            sun_steps.append(any(r.accepted for r in session.history[before:]))
        return out

    monkeypatch.setattr("worker.align.tracker.run_lm_stage", observed)
    estimates = recorded_estimates(monkeypatch)

    motion = Motion("turning", spin_deg=2.0, closing=0.0)
    seq = make_sequence(demo_model, Camera(**CAMERA), motion, 7, 11, "sun", fill=0.9)
    assert seq.request.options.fit_sun and seq.request.lighting is not None
    asked = seq.request.lighting.sun_direction
    tracker = Tracker(demo_model, seq.request)
    suns, status, unknowns, stepped = [], [], [], []
    for frame, truth in zip(seq.frames, seq.truths, strict=True):
        fits = len(sun_steps)
        result = tracker.track(frame.astype(np.float32) / 255.0, truth)
        stepped.append(any(sun_steps[fits:]))
        status.append("relearned" if result.relearned else result.status)
        memory = tracker._memory
        assert memory is not None, status
        fit = memory.session.fit
        if result.status == "reinitialised":
            # the next frames go on from features made afresh where the full estimate ended,
            # their rows learned there at full size (not the estimate's last set); the frame
            # reports where the pass from them ended (Tracker._full)
            view = memory.state.learned_at
            assert view is not None and view.level == 1.0
            ended = estimates[-1].session
            np.testing.assert_allclose(view.R, ended.R, atol=1e-12)
            np.testing.assert_allclose(view.t, ended.t, atol=1e-12)
        else:
            assert fit is not None, status
        assert list(memory.session.requested_lighting.sun_direction) == pytest.approx(asked)
        suns.append(np.asarray(memory.session.renderer.lighting.sun_direction))
        unknowns.append(fit.J.shape[1] if fit else 0)  # 8: the pose and the sun's tilt
    assert "relearned" in status[1:] and "tracked" in status[1:], status
    moved = [float(np.linalg.norm(b - a)) for a, b in zip(suns[:-1], suns[1:], strict=True)]
    for k in range(1, len(suns)):
        if status[k] == "relearned":
            assert unknowns[k] == 8, (k, status, unknowns)
        elif status[k] == "tracked":
            assert unknowns[k] == 6 and moved[k - 1] == 0.0, (k, status, unknowns, moved)
    # The request's sun is 4° off: solved again, a step the fit takes moves the tilt (on an
    # Intel Xeon VM one relearning took one; on an AMD EPYC VM both relearnings rejected both
    # trials, their cost already 0.002 px², and kept the sun).
    relearned = [k for k in range(1, len(suns)) if status[k] == "relearned"]
    assert len(sun_steps) >= len(relearned), (sun_steps, status)
    for k in relearned:
        assert (moved[k - 1] > 1e-4) == stepped[k], (k, moved, stepped, status)


@pytest.mark.slow
def test_a_frame_still_moving_when_its_iterations_run_out_goes_on_from_fresh_rows(
    demo_model: LoadedModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A tracked frame whose LM stopped still moving (its iterations ran out) but whose render
    aligns learns its rows afresh where it got to and goes on (Tracker._relearn), a tracked
    frame, not a full estimate. Here every frame's first pass may take one trial only, and the
    target turns 2° a frame, so the frames that start behind run out."""
    from schemas.camera import Camera
    from worker.align.session import Session
    from worker.align.tracker import CONVERGED, UNFINISHED, Tracker
    from worker.bench.sequences import Motion, make_sequence

    first: list[str] = []  # the first pass's stop rule, per tracked frame
    real_lm = Tracker._lm

    def one_trial(session: Session, state: Any) -> str:
        session.options = session.options.model_copy(update={"max_iterations": 1})
        first.append(real_lm(session, state))
        return first[-1]

    monkeypatch.setattr(Tracker, "_lm", staticmethod(one_trial))
    motion = Motion("turning", spin_deg=2.0, closing=0.05)
    seq = make_sequence(demo_model, Camera(**CAMERA), motion, 5, 17, "tone", fill=0.9)
    tracker = Tracker(demo_model, seq.request)
    went_on = 0
    for k, (frame, truth) in enumerate(zip(seq.frames, seq.truths, strict=True)):
        passes = len(first)
        result = tracker.track(frame.astype(np.float32) / 255.0, truth)
        if k == 0 or first[passes] not in UNFINISHED:
            continue
        # still moving after one trial: went on, and a tracked frame when that converged
        assert result.status in ("tracked", "reinitialised"), (k, result.status)
        if result.status == "tracked":
            went_on += 1
            assert result.relearned and result.reason in CONVERGED, (k, result.reason)
            assert result.errors is not None and result.errors.rotation_deg < 1.0, result.errors
            memory = tracker._memory
            assert memory is not None
            np.testing.assert_allclose(memory.learned_pose[0], result.R, atol=1e-12)
    assert went_on >= 1, first


@pytest.mark.slow
def test_a_full_estimate_goes_on_with_a_pass_from_fresh_rows(
    demo_model: LoadedModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A re-initialised frame (here the first) is the full estimate finished by a relearning
    frame's pass: features and rows made afresh where the estimate ended, an LM pass from
    them. The frame reports where that pass ended (and its render's score), and the next frame
    goes on from the rows learned there."""
    from schemas.camera import Camera
    from worker.align.estimator import errors_between
    from worker.align.tracker import TRACK_ROBUST_FLOOR_PX, Tracker
    from worker.bench.sequences import Motion, make_sequence

    estimates = recorded_estimates(monkeypatch)
    seq = make_sequence(
        demo_model, Camera(**CAMERA), Motion("still", 0.5, 0.0), 1, 23, "tone", fill=0.9
    )
    tracker = Tracker(demo_model, seq.request)
    result = tracker.track(seq.frames[0].astype(np.float32) / 255.0, seq.truths[0])
    assert result.status == "reinitialised" and result.converged
    [est] = estimates
    memory = tracker._memory
    assert memory is not None
    passed = memory.session
    assert passed is not est.session and len(passed.history) >= 1  # the pass ran
    # the estimate and the pass weigh features with the tracker's robust scale floor
    assert est.session.robust_floor_px == passed.robust_floor_px == TRACK_ROBUST_FLOOR_PX
    np.testing.assert_allclose(result.R, passed.R, atol=1e-12)
    np.testing.assert_allclose(memory.learned_pose[0], passed.R, atol=1e-12)
    assert result.renders == est.result.renders + passed.renders
    before = errors_between(seq.truths[0], est.session.R, est.session.t)
    assert result.errors is not None and before is not None
    # The pass refines; at 192 × 144 it may move either way by a few hundredths of a degree.
    assert result.errors.rotation_deg < max(2 * before.rotation_deg, before.rotation_deg + 0.1)
    assert result.errors.rotation_deg < 1.0, (before, result.errors)
