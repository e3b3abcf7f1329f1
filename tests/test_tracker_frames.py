"""A tracked frame's session (worker/align/tracker.py), no Mitsuba: what it inherits from the
previous frame's and what it sets for itself."""

from __future__ import annotations

import numpy as np
from test_refine import R0, T0, make_session

from worker.align.session import Session
from worker.align.tracker import FRAME_ITERATIONS, TRACK_PERTURBATION_SPP, Tracker


def _tracked_session(perturbation_spp: int) -> tuple[Session, list[int]]:
    """A tracked frame's session after a previous frame's with ``perturbation_spp``, and the
    samples per pixel of each render it makes."""
    previous = make_session(perturbation_spp=perturbation_spp)
    spps: list[int] = []
    render = previous.renderer.render

    def counted(*args: object, **kwargs: object) -> np.ndarray:
        spps.append(int(kwargs["spp"]))  # type: ignore[call-overload]
        return render(*args, **kwargs)  # type: ignore[arg-type]

    previous.renderer.render = counted  # type: ignore[method-assign]
    tracker = Tracker.__new__(Tracker)
    tracker.should_cancel = None
    tracker._points = np.zeros((1, 3), np.float32)  # the stub renderer has no window sensors
    image = np.zeros((64, 64, 3), np.float32)
    return tracker._session(previous, image, (R0, T0), None), spps


def test_a_tracked_frame_learns_from_perturbations_with_the_tracker_spp() -> None:
    session, spps = _tracked_session(perturbation_spp=4)
    assert session.options.perturbation_spp == TRACK_PERTURBATION_SPP
    assert session.options.max_iterations == FRAME_ITERATIONS
    session.render_perturbed(R0, T0, seed=1)
    assert spps == [TRACK_PERTURBATION_SPP]


def test_more_samples_asked_for_are_kept() -> None:
    session, _ = _tracked_session(perturbation_spp=4 * TRACK_PERTURBATION_SPP)
    assert session.options.perturbation_spp == 4 * TRACK_PERTURBATION_SPP
