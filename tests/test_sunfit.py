"""The sun-tilt parameterisation (worker/align/sunfit.py); the fit itself is checked on a real
estimate in test_estimate.py (test_default_estimate_fits_the_sun)."""

from __future__ import annotations

import contextlib
from types import SimpleNamespace

import numpy as np
import pytest

from worker.align.sunfit import MAX_TILT_DEG, PRIOR_PX_PER_RAD, SunTilt, tangent_basis
from worker.engine.renderer import LightingSpec


class _Renderer:
    """Holds a lighting, as the real renderer does (set_lighting / lighting)."""

    def __init__(self, lighting: LightingSpec) -> None:
        self.lighting = lighting

    def set_lighting(self, lighting: LightingSpec) -> None:
        self.lighting = lighting


def _tilt(sun: tuple[float, float, float], now: tuple[float, float, float] | None = None):  # noqa: ANN202
    asked = LightingSpec(sun, 3.0, 0.02)
    renderer = _Renderer(LightingSpec(now, 3.0, 0.02) if now else asked)
    return SunTilt(SimpleNamespace(requested_lighting=asked, renderer=renderer)), renderer  # type: ignore[arg-type]


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


@pytest.mark.parametrize("d", [[0, 0, 1], [1, 0, 0], [0.48, -0.36, -0.8], [0.99, 0.1, 0.0]])
def test_tangent_basis_is_orthonormal(d: list[float]) -> None:
    d = np.asarray(d, dtype=np.float64) / np.linalg.norm(d)
    e1, e2 = tangent_basis(d)
    M = np.stack([d, e1, e2])
    np.testing.assert_allclose(M @ M.T, np.eye(3), atol=1e-12)


def test_tilt_moves_the_sun_by_its_angle_and_keeps_the_rest() -> None:
    sun, renderer = _tilt((0.48, -0.36, -0.8))
    np.testing.assert_allclose(sun.ab, 0.0, atol=1e-12)  # starts at the requested sun
    ab = np.tan(np.radians([3.0, 0.0]))
    sun.set(ab)
    d = np.asarray(renderer.lighting.sun_direction)
    assert np.linalg.norm(d) == pytest.approx(1.0)
    assert (
        _angle(d, sun.s0)
        == pytest.approx(3.0, abs=1e-9)
        == np.degrees(np.arctan(np.linalg.norm(sun.ab)))
    )
    assert renderer.lighting.sun_irradiance == 3.0 and renderer.lighting.ambient == 0.02


def test_a_later_stage_starts_from_the_sun_in_use() -> None:
    first, renderer = _tilt((0.0, -0.6, -0.8))
    first.set(np.array([0.03, -0.05]))
    second = SunTilt(SimpleNamespace(requested_lighting=first.requested, renderer=renderer))  # type: ignore[arg-type]
    np.testing.assert_allclose(second.ab, [0.03, -0.05], atol=1e-12)
    np.testing.assert_allclose(second.direction(), renderer.lighting.sun_direction, atol=1e-12)


def test_clip_caps_the_tilt_and_the_prior_pulls_back() -> None:
    sun, _ = _tilt((0.0, 0.0, -1.0))
    far = np.tan(np.radians(25.0)) * np.array([0.6, 0.8])
    clipped = sun.clip(far)
    assert np.degrees(np.arctan(np.linalg.norm(clipped))) == pytest.approx(MAX_TILT_DEG)
    np.testing.assert_allclose(clipped / np.linalg.norm(clipped), [0.6, 0.8])
    np.testing.assert_allclose(sun.clip(far / 10), far / 10)  # 2.5°: unchanged
    sun.set(np.array([0.02, -0.01]))
    Jp, rp = sun.prior_rows()
    assert Jp.shape == (2, 8) and not Jp[:, :6].any()
    # A step of -ab on the tilt zeroes the prior's residual: it pulls towards the request.
    np.testing.assert_allclose(rp - Jp @ np.r_[np.zeros(6), -sun.ab], 0.0, atol=1e-12)
    assert Jp[0, 6] == Jp[1, 7] == PRIOR_PX_PER_RAD


def _scripted_session(sun_dir: tuple[float, float, float]):  # noqa: ANN202
    """A session whose renders record the sun they were made under, and a ``measure`` that
    scripts three features: 0 moves with the sun's tilt along e1, 1 is geometry (never
    moves), 2 is found only under the requested sun (a shadow edge a tilt moves away)."""
    asked = LightingSpec(sun_dir, 3.0, 0.02)
    renderer = _Renderer(asked)
    session = SimpleNamespace(
        requested_lighting=asked,
        renderer=renderer,
        options=SimpleNamespace(min_features=2, reuse_jacobian=True),
        timed=lambda part: contextlib.nullcontext(),
        render_view=lambda R, t: SimpleNamespace(sun=np.asarray(renderer.lighting.sun_direction)),
    )
    tilt = SunTilt(session)  # type: ignore[arg-type]

    def measure(view: SimpleNamespace, guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        a = float(view.sun @ tilt.e1)  # the tilt along e1 (radians, small)
        h = np.array([[100.0 + 50.0 * a, 40.0], [60.0, 80.0], [20.0, 30.0]])
        found = np.array([True, True, abs(float(view.sun @ tilt.s0) - 1.0) < 1e-12])
        return h, found

    return session, tilt, measure


def test_features_a_tilted_sun_loses_get_no_sun_motion_and_leave_the_fit() -> None:
    from worker.align.refine import StageState, _ready_state

    session, tilt, measure = _scripted_session((0.48, -0.36, -0.8))
    view = SimpleNamespace(R=np.eye(3), t=np.zeros(3))
    h, ok = measure(session.render_view(None, None), None)
    Js, seen = tilt.jacobian(measure, view, h, ok)  # type: ignore[arg-type]
    assert seen.tolist() == [True, True, False]
    assert Js[0, 0] == pytest.approx(50.0, rel=1e-3) and abs(Js[0, 1]) < 1e-3  # moves along e1
    assert not Js[2:4].any() and not Js[4:6].any()  # geometry: no motion; lost: no rows

    def ready() -> StageState:
        """A stage's state with its rows learned at ``view``, made ready with the sun."""
        st = StageState(SimpleNamespace(measure=measure), h, ok, learned=object(), learned_at=view)  # type: ignore[arg-type]
        return _ready_state(session, st, "klt", view, tilt)  # type: ignore[arg-type]

    # the stage's fit keeps the feature the sun moves and the geometric one, not the lost one
    st = ready()
    assert st.ok.tolist() == [True, True, False] and st.sun_J is not None
    # unless that would leave fewer features than the fit needs: then all stay
    session.options.min_features = 3
    assert ready().ok.tolist() == [True, True, True]
