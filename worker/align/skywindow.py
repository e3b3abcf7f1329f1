"""A tracked frame's sky window: its renders render only the target, pasted onto the sky.

A tracked frame (worker.align.tracker) starts at a prediction a fraction of a degree off, so
where the target is in its image is known before anything is rendered: inside the image of the
model's vertices at the prediction. Its renders (the main ones and the perturbations it learns a
Jacobian from) render a square of the refinement's window ladder (worker.align.pyramid) around
those bounds and paste it onto the sky (``Session.sky_window``), so every position stays in the
whole image's pixels while a render costs the square's: a spacecraft half the frame across
costs a third of a whole render. The renderer has those sensors because the tracker's full
estimates ask for them (``estimate(…, window_sensors=True)``).

The whole image is rendered instead when the window would not hold the target: a vertex behind
the camera (the camera inside the model's bounds: terrain, docking range), bounds no ladder
side holds (a target filling the frame), or light in the reference outside the window (the
target is not where predicted, e.g. after a jump).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from worker.align.pyramid import ladder_side
from worker.align.session import LIT_FRACTION, Session
from worker.engine.meshes import LoadedModel

Array = NDArray[np.float64]
SkyWindow = tuple[int, tuple[float, float]]

#: Lit pixels of the reference outside the window, as a fraction of those inside, above which
#: the frame is rendered whole: the reference's noise stays far below it.
SKY_SPILL = 0.01
#: A frame keeps the previous frame's window side while that is at most this many times the
#: side it needs (two steps of the ladder): a side's first renders compile its kernels, and a
#: tumbling target's bounds would otherwise move between sides from frame to frame.
SKY_KEEP = 2.0**0.5 + 1e-6


def outline_points(model: LoadedModel) -> NDArray[np.float32]:
    """The model's vertices (model frame, float32) that bound its image at any pose: those of
    their convex hull, for the extremes of a projection over a convex set lie at its vertices
    (as do those of the depth); the bounds are the same as all the vertices give, at a fraction
    of the cost (the ISS: 73 of 101,363, ~10 ms a frame less). All of them when SciPy is not
    installed or the hull is degenerate (a flat model)."""
    points = np.concatenate([p.vertices for p in model.parts]).astype(np.float32)
    try:
        from scipy.spatial import ConvexHull

        return points[np.sort(ConvexHull(points.astype(np.float64)).vertices)]
    except (ImportError, RuntimeError, ValueError):  # no SciPy; QhullError; too few points
        return points


def sky_window(
    points: NDArray[np.float32],
    session: Session,
    pose: tuple[Array, Array],
    keep: int | None = None,
) -> SkyWindow | None:
    """(ladder side, centre in px) of the window for ``session``'s renders near ``pose``: the
    smallest side that holds the projected bounds of ``points`` (the model's vertices; the
    ladder's margin holds the LM's moves within a frame), or ``keep`` while that is at most
    SKY_KEEP times larger, centred on the bounds. None: render the whole image (see the module
    docstring)."""
    renderer = session.renderer
    if not renderer.window_sides:
        return None
    R, t = pose
    X = points @ R.T.astype(np.float32) + t.astype(np.float32)
    if float(X[:, 2].min()) <= 0.0:
        return None
    uv = renderer.camera.project(X)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    side = ladder_side(renderer.window_sides, float((hi - lo).max()))
    if side is not None and keep is not None and side <= keep <= SKY_KEEP * side:
        side = keep
    centre = (float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2)
    window = None if side is None else renderer.window_at(1.0, side, centre)
    if window is None:
        return None
    (x, y), (w, h) = window.origin, renderer.window_sizes[(window.side, 1.0)]
    reference = session.reference_grey
    lit = reference > LIT_FRACTION * float(reference.max())
    inside = int(lit[y : y + h, x : x + w].sum())
    return (window.side, centre) if int(lit.sum()) - inside <= SKY_SPILL * inside else None
