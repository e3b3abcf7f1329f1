"""A tracked frame's rows measured along its weakest direction (worker/align/weakprobe.py), on
real renders: rows that overstate the motion there are corrected, and the step taken again
goes most of the way to where the rows as learned end, which the overstated rows stopped short
of."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from worker.engine.meshes import LoadedModel

CAMERA = {"width": 192, "height": 144, "fx": 230.0, "fy": 230.0, "cx": 95.5, "cy": 71.5}


def _weakest_direction(session: Any, state: Any) -> tuple[np.ndarray, np.ndarray]:
    """The geometry's weakest direction at the session's pose (raw increment units, scaled to
    1 rad / one range), and the features' ray-cast rows."""
    from worker.align.learning import analytic_jacobian
    from worker.align.lm import rows_of, whiten

    features = state.features
    geo = analytic_jacobian(session, state.h, features.feature_normals).J
    hit = state.ok & np.isfinite(geo).reshape(-1, 2, 6).all(axis=(1, 2))
    scale = np.concatenate([np.full(3, 2.0), np.full(3, 1.0 / session.range_)])
    G = whiten(features.A[hit], geo[rows_of(hit)]) / scale
    _, V = np.linalg.eigh(G.T @ G)
    return V[:, 0] / scale, geo


@pytest.mark.slow
def test_rows_that_overstate_the_weakest_direction_are_measured_and_the_step_reaches_further(
    demo_model: LoadedModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The second frame of a sequence starts 0.6° (in rotation and range-scaled translation)
    along the geometry's weakest direction from its truth, with the carried rows made to
    predict three times the geometric motion along it (what noisy learned rows do along a
    near-cancellation: bench/README.md, "A tracked frame's rows measured along its weakest
    direction"). The frame's LM alone stops short of where the rows as learned take it; with
    the probe the rows along the direction come back near the geometry's and the step goes
    most of the way there.

    Measured from where the rows as learned end, not from the truth: along the weakest
    direction the end is where the features' small photometric offsets put it, which differs
    between CPUs (Dr.Jit compiles for the host): on one the ends lay near the truth (the LM
    alone 0.21° of the 0.6° left, with the probe −0.03°), on an AMD Zen 2 the rows as learned
    end 0.47° past the truth, the LM alone at 0.17° and with the probe at −0.25°."""
    import worker.align.tracker as tracker_module
    from schemas.camera import Camera
    from worker.align.tracker import Tracker
    from worker.bench.sequences import Motion, make_sequence
    from worker.engine.posemath import apply_increment, increment_between

    motion = Motion("turning", spin_deg=1.0, closing=0.0)
    seq = make_sequence(demo_model, Camera(**CAMERA), motion, 2, 5, "plain", fill=0.9)
    tracker = Tracker(demo_model, seq.request)
    first = tracker.track(seq.frames[0].astype(np.float32) / 255.0, seq.truths[0])
    assert first.status == "reinitialised" and tracker._memory is not None
    memory = tracker._memory
    image = seq.frames[1].astype(np.float32) / 255.0
    R1, t1 = seq.truths[1]

    probed: list[bool] = []

    def frame(probe: bool, overstate: float = 2.0) -> tuple[float, float]:
        """The second frame's LM (with or without the probe) from the offset start, the rows
        along the direction ``overstate`` times the geometric motion too large; returns the
        offset left along the direction (degrees, from the truth) and how far the rows along
        the direction overstate the geometric motion."""

        def recorded(session: Any) -> bool:
            probed.append(real(session))
            return probed[-1]

        monkeypatch.setattr(
            tracker_module, "probe_weak_directions", recorded if probe else lambda s: False
        )
        at_truth = tracker._session(memory.session, image, (R1, t1), seq.truths[1])
        d, _ = _weakest_direction(at_truth, tracker._carry(memory, at_truth))
        start = apply_increment(R1, t1, d * np.radians(0.6))
        session = tracker._session(memory.session, image, start, seq.truths[1])
        state = tracker._carry(memory, session)
        _, geo = _weakest_direction(session, state)
        J = state.learned.J
        known = np.isfinite(J).all(axis=1) & np.isfinite(geo).all(axis=1)
        J[known] += np.outer(overstate * (geo[known] @ d), d / (d @ d))
        Tracker._lm(session, state)
        left = increment_between(R1, t1, session.R, session.t)
        rows = session.last_stage.learned.J
        overstated = np.linalg.norm(rows[known] @ d) / np.linalg.norm(geo[known] @ d)
        along = float(np.degrees(left @ d / (d @ d)))
        return along, float(overstated)

    real = tracker_module.probe_weak_directions
    along_learned, _ = frame(probe=False, overstate=0.0)
    along_lm, overstated_lm = frame(probe=False)
    along_probe, overstated_probe = frame(probe=True)
    assert probed == [True]
    assert overstated_lm > 2.0, overstated_lm  # the rows as the LM leaves them
    assert 0.5 < overstated_probe < 1.6, overstated_probe  # measured back near the geometry's
    # Short of the end of the rows as learned (measured on a Zen 2: 0.64° short alone, 0.22°
    # with the probe; on another CPU, from the truth, 0.21° and 0.03°).
    short_lm, short_probe = abs(along_lm - along_learned), abs(along_probe - along_learned)
    assert short_lm > 0.15, (along_lm, along_learned)
    assert short_probe < 0.5 * short_lm, (along_probe, along_lm, along_learned)
