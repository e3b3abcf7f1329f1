"""The geometric pass: once the learned-Jacobian passes have converged, one more LM pass on the
last pass's features with the Jacobian from the model's geometry, kept only when the reference's
features, measured afresh, fit its pose better.

Why. The learned rows fit the image motion of perturbed renders (half size, 4 spp), and their
tracking noise is a few per cent of each column. Where a target is seen nearly flat, an
out-of-plane rotation and a lateral shift move the features almost alike, so the direction that
trades one for the other moves them by a few hundredths of what either does alone: the learned
rows get that cancellation wrong by more than it is (measured on the demo satellite: for the
step from where an estimate stopped to the truth, 1.25° away, the learned rows predicted 1.19 px
rms of feature motion, the renders showed 0.16 px). The LM then proposes steps the trial renders
refuse and stops there, "converged", with a covariance that calls that direction well seen. The
rows from ray-cast geometry (as the 'fast' method uses) get the cancellation right; each step is
still checked by a trial render as in any LM pass, and the pass is undone when the features fit
worse afterwards. A kept pass that turns the attitude far (options.geometric_recheck_deg) shows
the learned passes stopped short: one more learned pass runs from its pose, and this pass again
(:func:`geometric_passes`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np

from worker.align.refine import Outcome, run_lm_stage
from worker.align.session import RenderedView, Session
from worker.align.tracked import Features
from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.metrics import rotation_error_deg
from worker.engine.posemath import increment_between, step_norm

#: Learned passes (each followed by the geometric pass again) that a geometric pass's large
#: move earns at most (options.geometric_recheck_deg).
MAX_RECHECKS = 2

#: Fraction of the features (the best-fitting ones) whose misfit judges the pass: the rest
#: are the outliers any pose leaves.
JUDGED_FRACTION = 0.8


def geometric_passes(
    session: Session, learned_pass: Callable[[], Outcome], outcome: Outcome
) -> Outcome:
    """The geometric pass after the learned ones, and again after one more learned pass while
    it is kept and turns the attitude by more than options.geometric_recheck_deg (at most
    MAX_RECHECKS times): such a move shows the learned passes stopped short, "converged" on
    rows that miss a weakly seen direction, and the geometric pass itself stops on the
    learned pass's features (made where that pass began). Found on Aura's solar array seen
    edge-on (a tumble sequence's frame, `combined`, from 1° off): the learned passes stopped
    1.24° off, the geometric pass took it to 0.56°, one more learned pass to 0.09°.

    Returns the stop rule of the last pass that moved the pose: a kept geometric pass's own
    (a learned pass that ended 'slow', still moving, and a geometric pass that then stopped
    because no step lowered the cost any more is a converged estimate), else ``outcome``,
    the learned passes'."""
    for recheck in range(MAX_RECHECKS + 1):
        before = session.R.copy()
        kept, stop = run_geometric_pass(session)
        if not kept:
            break
        outcome = stop or outcome
        turned = rotation_error_deg(before, session.R)
        limit = session.options.geometric_recheck_deg
        if recheck == MAX_RECHECKS or not 0 < limit < turned or session.iterations_left <= 0:
            break
        try:
            outcome = learned_pass()
        except TooFewFeaturesError:
            break  # the geometric pass's pose stands
    return outcome


def run_geometric_pass(session: Session) -> tuple[bool, Outcome | None]:
    """Run the geometric pass from the session's pose; returns whether its pose was kept,
    and the stop rule its LM stage ended on (None when too few features ended it).

    Nothing happens without a learned stage of reference features to continue ('klt'), with
    the Jacobian already geometric ('fast'), with no iteration left, or when that stage's
    features were made at another level than the session's (the full-resolution passes found
    too few features and the coarse pass's pose stands: its features' pixels are not the
    renders'). Too few features with geometric rows (most of them on the silhouette against
    the sky, where a ray hits nothing) end the pass where it is, like any other stop.
    """
    learned = session.last_stage
    opts = session.options
    if (
        learned is None
        or opts.refine_features != "klt"
        or opts.jacobian == "analytic"
        or session.iterations_left <= 0
        or learned.level != session.level
    ):
        return False, None
    start_view, start_fit = session.current_view(), session.fit
    state = copy.copy(learned)
    state.learned = None  # the stage makes the geometric rows at its first iteration
    session.options = opts.model_copy(update={"jacobian": "analytic"})
    stop: Outcome | None = None
    try:
        stop = run_lm_stage(session, "klt", "refine", fit_sun=False, state=state)
    except TooFewFeaturesError:
        pass
    finally:
        session.options = opts
    end_view = session.current_view()
    if end_view is start_view:  # no step was accepted: the learned pass's fit stands
        session.fit, session.last_stage = start_fit, learned
        return False, stop
    after, before, n = misfits(learned.features, end_view, start_view)
    if after < before:
        return True, stop
    # Undone: back to the learned passes' pose, recorded as a move (the history's last
    # accepted pose stays the result's).
    session.accept(start_view)
    session.fit, session.last_stage = start_fit, learned
    back = increment_between(end_view.R, end_view.t, start_view.R, start_view.t)
    session.record("refine", before, step_norm(back, session.range_), 0.0, True, n)
    return False, stop


def misfits(features: Features, a: RenderedView, b: RenderedView) -> tuple[float, float, int]:
    """How well ``features`` fit in views ``a`` and ``b``: the mean whitened squared residual
    of the best-fitting JUDGED_FRACTION of the features found in both (inf, inf when none),
    and how many were found in both."""
    h_a, ok_a = features.measure(a, None)
    h_b, ok_b = features.measure(b, None)
    both = ok_a & ok_b
    n = int(JUDGED_FRACTION * both.sum())
    if n == 0:
        return float("inf"), float("inf"), 0

    def trimmed(h: np.ndarray) -> float:
        r = np.einsum("kij,kj->ki", features.A[both], (features.x_ref - h)[both])
        return float(np.sort((r**2).sum(axis=1))[:n].mean())

    return trimmed(h_a), trimmed(h_b), int(both.sum())
