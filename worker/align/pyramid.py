"""Coarse to fine: at which image scales the stages of an estimate work.

A render costs about its pixel count, and so do the image operations around it (matching,
contrast normalisation, tracking). The coarse stage and the first refinement pass only have to
bring the pose within the last pass's reach, so they work on a reduced image: the reference
area-averaged onto the camera scaled exactly (principal point and skew included, see
``PinholeCamera.scaled``), rendered with a sensor of that size. Only the last pass (and any
pass a 'slow' one earns) works at the reference's resolution. Levels are powers of two, the
smallest whose short side and target keep a floor (COARSE_*, FIRST_PASS_*). When PnP finds too
few descriptor matches at the coarse level (a thin target, far off), the coarse stage tries
again at full resolution (worker.align.estimator).

Once the coarse stage has placed the target, the refinement needs only the part of the image
the target covers: its levels get a *window*, a square around the target's lit part with a
margin (:func:`ladder_side`), rendered and processed instead of the whole image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from worker.engine.camera import PinholeCamera

#: Shortest image side and smallest apparent target diameter of the first refinement pass's
#: level, px.
FIRST_PASS_SIDE_PX, FIRST_PASS_TARGET_PX = 240, 120
#: The same for the coarse stage's level: the first pass's. Twice these (the coarse stage at
#: full resolution up to ~960 px) cost twice the renders at 512–640 px for the same accuracy
#: (`proxpose bench --models iss,aura,phobos --bands 3,10,20 --cases 2 --size 512,640x480
#: --methods default`: render cost 6.1 → 3.3 full renders at 512², 5.4 → 2.6 at 640×480; median
#: rotation 0.035° → 0.038°, 0.036° → 0.045°; 36/36 converged).
COARSE_SIDE_PX, COARSE_TARGET_PX = FIRST_PASS_SIDE_PX, FIRST_PASS_TARGET_PX
#: Shortest side of a perturbation render, px (a small image halved leaves the tracker too
#: little to learn from).
MIN_PERTURBATION_SIDE_PX = 256
#: The refinement's window is a square picked from a ladder of sides, fractions of the image's
#: short side (2^(-k/4), k = 1…8): each side is a sensor of fixed film size, shared by every
#: estimate with that camera (and its compiled kernels with it), the chosen one at most 19 %
#: larger than needed.
WINDOW_LADDER = tuple(2.0 ** (-k / 4.0) for k in range(1, 9))
#: The side needed: the target's lit extent in the render after the coarse stage times
#: WINDOW_MARGIN, plus WINDOW_PAD_PX (the pose is then within about a degree and a per cent of
#: range; the margin keeps what the reference shows lit beyond the render's lit part).
WINDOW_MARGIN = 1.1
WINDOW_PAD_PX = 16


@dataclass(frozen=True)
class LevelPlan:
    """The levels of the coarse stage and of the first refinement pass (the later passes work
    at full resolution) and, per level, the scale of its perturbation renders."""

    coarse: float
    first_pass: float
    perturbation: dict[float, float]
    #: Film size (w, h) of each window sensor, keyed (ladder side, scale) (empty: no window).
    windows: dict[tuple[int, float], tuple[int, int]] = field(default_factory=dict)

    @property
    def scales(self) -> tuple[float, ...]:
        """Every scale a renderer needs a sensor for, full resolution first."""
        levels = {1.0, self.coarse, self.first_pass, *self.perturbation.values()}
        return tuple(sorted(levels, reverse=True))


def level_spp(spp: int, level: float, floor: int) -> int:
    """Samples per pixel of a main render at ``level``: as many per unit of image area as
    ``spp`` gives at full resolution (spp·level²), but at least ``floor`` (or spp, if
    smaller). The reference is area-averaged onto a level's camera, so such a render has the
    noise of a full-resolution one averaged the same way, at level² of its cost."""
    return max(min(spp, floor), round(spp * level * level))


def perturbation_scale(requested: float, level: float, camera: PinholeCamera) -> float:
    """The perturbation renders' scale at ``level``: ``requested`` of the level, but never
    below MIN_PERTURBATION_SIDE_PX on the short side, nor above the level itself."""
    floor = MIN_PERTURBATION_SIDE_PX / min(camera.width, camera.height)
    return min(level, round(max(requested * level, floor), 3))


def level_for(camera: PinholeCamera, target_px: float, side_px: float, across_px: float) -> float:
    """The smallest power-of-two scale that keeps the short side at ``side_px`` and the target
    (``target_px`` across at full resolution) at ``across_px``; at most 1."""
    side = min(camera.width, camera.height)
    need = max(side_px / side, across_px / max(target_px, 1e-9))
    return min(1.0, 2.0 ** math.ceil(math.log2(need)))


def plan_levels(
    camera: PinholeCamera,
    target_px: float,
    perturbation: float,
    pyramid: bool,
    window: bool = False,
) -> LevelPlan:
    """The levels of one estimate (``pyramid`` False: everything at full resolution), with
    the window sensors of the refinement's levels when ``window`` is set."""
    coarse = first = 1.0
    if pyramid:
        coarse = level_for(camera, target_px, COARSE_SIDE_PX, COARSE_TARGET_PX)
        first = level_for(camera, target_px, FIRST_PASS_SIDE_PX, FIRST_PASS_TARGET_PX)
    levels = {first, 1.0}  # the levels that learn a Jacobian
    scales = {lv: perturbation_scale(perturbation, lv, camera) for lv in levels}
    windows = plan_windows(camera, levels | set(scales.values())) if window else {}
    return LevelPlan(coarse, first, scales, windows)


def plan_windows(
    camera: PinholeCamera, scales: set[float]
) -> dict[tuple[int, float], tuple[int, int]]:
    """Film sizes (w, h) of the window sensors: one per ladder side (full-resolution px, see
    WINDOW_LADDER) and scale in ``scales``, keyed (side, scale); a window is square, clipped
    to the scaled image."""
    short = min(camera.width, camera.height)
    sizes = {}
    for fraction in WINDOW_LADDER:
        side = round(fraction * short)
        for s in scales:
            cam = camera if s == 1.0 else camera.scaled(s)
            n = math.ceil(side * s) + 2
            sizes[(side, s)] = (min(cam.width, n), min(cam.height, n))
    return sizes


def ladder_side(sides: list[int], extent_px: float) -> int | None:
    """The smallest ladder side that holds a target of lit extent ``extent_px`` (full-
    resolution px) with its margin; None when none does (the whole image is used)."""
    need = WINDOW_MARGIN * extent_px + WINDOW_PAD_PX
    fitting = [side for side in sides if side >= need]
    return min(fitting) if fitting else None
