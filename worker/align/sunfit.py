"""The sun direction as two more unknowns of the refinement.

A request's sun direction comes from an ephemeris and an attitude estimate, and is a few
degrees off. Features that shading makes (a terminator, a shadow edge, the bright side of a
curved panel) then sit elsewhere in the reference than in our render, and with the pose alone
to explain them the pose takes the difference. So the refinement also solves for a tilt of the
sun: each feature's motion per tilt is measured from two renders at the current pose with the
sun tilted (a purely geometric feature does not move, a shading feature does), the two columns
join the pose Jacobian, and the LM step moves pose and sun together. A photometric fit of the
sun cannot do this: a reference from another renderer (inter-reflections, another BRDF) differs
in brightness everywhere, and the best-matching shading is then far from the true sun.

The tilt (a, b) is in radians along two fixed directions e1, e2 perpendicular to the requested
sun s0: s = normalise(s0 + a e1 + b e2).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from worker.align.lm import lm_step
from worker.align.session import RenderedView, Session
from worker.engine.renderer import LightingSpec

Array = NDArray[np.float64]
#: ``Features.measure``: positions (k, 2) of the features in a render, and which were found.
Measure = Callable[[RenderedView, Array | None], tuple[Array, NDArray[np.bool_]]]

#: Sun tilt of the two renders that measure the features' motion, degrees.
TILT_STEP_DEG = 2.0
#: Weight of the requested direction, px of residual per radian of tilt: a 5° tilt costs as
#: much as one feature 0.3 px off, so hundreds of features outweigh it, but a sun the features
#: cannot see (no shading features) stays where the request put it.
PRIOR_PX_PER_RAD = 3.4
#: Largest tilt from the requested sun, degrees (a larger one is cut back to it).
MAX_TILT_DEG = 10.0


def tangent_basis(d: Array) -> tuple[Array, Array]:
    """Two unit vectors perpendicular to ``d`` and to each other."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


class SunTilt:
    """The sun of an estimate: the requested direction and the current tilt from it."""

    def __init__(self, session: Session) -> None:
        self.session = session
        self.requested: LightingSpec = session.requested_lighting
        self.s0 = np.asarray(self.requested.sun_direction, dtype=np.float64)
        self.e1, self.e2 = tangent_basis(self.s0)
        # Start from the sun renders use now (an earlier stage may have tilted it).
        now = np.asarray(session.renderer.lighting.sun_direction, dtype=np.float64)
        self.ab = np.array([now @ self.e1, now @ self.e2]) / max(float(now @ self.s0), 1e-6)

    def direction(self, ab: Array | None = None) -> Array:
        a, b = self.ab if ab is None else ab
        v = self.s0 + a * self.e1 + b * self.e2
        return v / np.linalg.norm(v)

    def clip(self, ab: Array) -> Array:
        limit = np.tan(np.radians(MAX_TILT_DEG))
        n = float(np.linalg.norm(ab))
        return ab if n <= limit else ab * (limit / n)

    def set(self, ab: Array) -> None:
        """Render from now on with the sun tilted by ``ab``."""
        self.ab = np.asarray(ab, dtype=np.float64)
        sun = tuple(float(x) for x in self.direction())
        self.session.renderer.set_lighting(replace(self.requested, sun_direction=sun))

    def prior_rows(self) -> tuple[Array, Array]:
        """Two rows (Jacobian over [pose, tilt], residual) pulling the tilt towards zero."""
        Jp = np.zeros((2, 8))
        Jp[0, 6] = Jp[1, 7] = PRIOR_PX_PER_RAD
        return Jp, -PRIOR_PX_PER_RAD * self.ab

    def jacobian(
        self, measure: Measure, view: RenderedView, h: Array, ok: NDArray[np.bool_]
    ) -> tuple[Array, NDArray[np.bool_]]:
        """Image motion of each feature per radian of tilt along e1 and e2, (2k, 2), and which
        features both tilted renders show.

        ``measure(view, guess)`` finds the features in a render. A feature lost in a tilted
        render gets zero rows (no known motion), as do those not found at the current pose;
        the refinement leaves the lost ones out of its fit (worker.align.refine._ready_state).
        """
        step = np.tan(np.radians(TILT_STEP_DEG))
        cols = []
        keep = ok.copy()
        base = self.ab.copy()
        for e in (np.array([step, 0.0]), np.array([0.0, step])):
            self.set(base + e)
            tilted = self.session.render_view(view.R, view.t)
            h_e, ok_e = measure(tilted, h)
            keep &= ok_e
            cols.append(((h_e - h) / step).ravel())
        self.set(base)
        Js = np.column_stack(cols)
        Js[~np.repeat(keep, 2)] = 0.0
        return Js, keep


def step_with_sun(J: Array, r: Array, lam: float, w: Array, sun: SunTilt | None) -> Array:
    """The LM step over J's columns; with the sun's tilt among them, its prior joins the solve."""
    if sun is None:
        return lm_step(J, r, lam, w)
    Jp, rp = sun.prior_rows()
    return lm_step(np.vstack([J, Jp]), np.concatenate([r, rp]), lam, np.append(w, 1.0))
