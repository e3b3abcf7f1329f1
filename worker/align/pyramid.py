"""Coarse to fine: at which image scales the stages of an estimate work.

A render costs about its pixel count, and so do the image operations around it (matching,
contrast normalisation, tracking). The coarse stage and the first refinement pass only have to
bring the pose within the last pass's reach, so they work on a reduced image: the reference
area-averaged onto the camera scaled exactly (principal point and skew included, see
``PinholeCamera.scaled``), rendered with a sensor of that size. Only the last pass (and any
pass a 'slow' one earns) works at the reference's resolution. Levels are powers of two, the
smallest whose short side and target keep a floor: PnP on descriptor matches needs more pixels
(COARSE_*) than the first refinement pass, which starts within a few tenths of a degree
(FIRST_PASS_*).

Once the coarse stage has placed the target, the refinement needs only the part of the image
the target covers: its levels get a *window* (:func:`plan_windows`), a square around the
target's bounding sphere with a margin, rendered and processed instead of the whole image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from worker.engine.camera import PinholeCamera

#: Shortest image side and smallest apparent target diameter of the coarse stage's level, px.
COARSE_SIDE_PX, COARSE_TARGET_PX = 480, 240
#: The same for the first refinement pass's level, px.
FIRST_PASS_SIDE_PX, FIRST_PASS_TARGET_PX = 240, 120
#: Shortest side of a perturbation render, px (a small image halved leaves the tracker too
#: little to learn from).
MIN_PERTURBATION_SIDE_PX = 256
#: The refinement's window: the target's apparent diameter at the initial pose times
#: WINDOW_MARGIN (its range may be that much shorter, and a bounding sphere off the optical axis
#: projects larger) plus WINDOW_PAD_PX, rounded up to WINDOW_STEP_PX (renderers, and their
#: compiled kernels, are then shared by targets of about one size).
WINDOW_MARGIN = 1.2
WINDOW_PAD_PX = 24
WINDOW_STEP_PX = 64
#: A window covering more of the image than this is not used: the refinement takes the whole
#: image (a target filling the frame, terrain).
MAX_WINDOW_FRACTION = 0.75


@dataclass(frozen=True)
class LevelPlan:
    """The levels of the coarse stage and of the first refinement pass (the later passes work
    at full resolution) and, per level, the scale of its perturbation renders."""

    coarse: float
    first_pass: float
    perturbation: dict[float, float]
    #: Film size (w, h) of the refinement's window at each of its scales (empty: no window).
    windows: dict[float, tuple[int, int]] = field(default_factory=dict)

    @property
    def scales(self) -> tuple[float, ...]:
        """Every scale a renderer needs a sensor for, full resolution first."""
        levels = {1.0, self.coarse, self.first_pass, *self.perturbation.values()}
        return tuple(sorted(levels, reverse=True))


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
    windows for the refinement when ``window`` is set and the target leaves enough out."""
    coarse = first = 1.0
    if pyramid:
        coarse = level_for(camera, target_px, COARSE_SIDE_PX, COARSE_TARGET_PX)
        first = level_for(camera, target_px, FIRST_PASS_SIDE_PX, FIRST_PASS_TARGET_PX)
    levels = {first, 1.0}  # the levels that learn a Jacobian
    scales = {lv: perturbation_scale(perturbation, lv, camera) for lv in levels}
    windows = plan_windows(camera, target_px, levels | set(scales.values())) if window else {}
    return LevelPlan(coarse, first, scales, windows)


def plan_windows(
    camera: PinholeCamera, target_px: float, scales: set[float]
) -> dict[float, tuple[int, int]]:
    """Film sizes (w, h) of the window at each of ``scales``: a square WINDOW_MARGIN times the
    target's apparent diameter (``target_px``, full-resolution px) plus WINDOW_PAD_PX, rounded
    up to WINDOW_STEP_PX and clipped to the image; none when it would cover more than
    MAX_WINDOW_FRACTION of the image."""
    side = WINDOW_STEP_PX * math.ceil((WINDOW_MARGIN * target_px + WINDOW_PAD_PX) / WINDOW_STEP_PX)
    w, h = min(camera.width, side), min(camera.height, side)
    if w * h > MAX_WINDOW_FRACTION * camera.width * camera.height:
        return {}
    sizes = {}
    for s in scales:
        cam = camera if s == 1.0 else camera.scaled(s)
        sizes[s] = (min(cam.width, math.ceil(w * s) + 2), min(cam.height, math.ceil(h * s) + 2))
    return sizes
