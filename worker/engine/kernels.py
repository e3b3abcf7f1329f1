"""How a renderer calls Mitsuba: plainly, or replaying a recorded kernel (``dr.freeze``)."""

from __future__ import annotations

import os
from collections.abc import Callable

#: Frozen-render recordings per sensor before Dr.Jit warns (per spp; again after others' first).
RECORDINGS_PER_SENSOR = 6


def use_frozen(variant: str) -> bool:
    """Whether renders replay a recorded kernel (JIT variants, unless PROXPOSE_FROZEN=0)."""
    return not variant.startswith("scalar") and os.environ.get("PROXPOSE_FROZEN", "1") != "0"


def plain_render(scene: object, sensor: int, spp: int, seed: int) -> object:
    import mitsuba as mi

    return mi.render(scene, sensor=sensor, spp=spp, seed=seed)


def frozen_render(sensors: int = 1) -> Callable[[object, int, int, int], object]:
    """``mi.render`` under ``dr.freeze``: the first calls per (sensor, spp) record the kernel
    launches, later ones replay them with the scene's current parameters (pose, lights, the
    seed, which goes in opaque: as a literal, another seed recorded every render again) and skip
    tracing, which grows with every part and texture of a model (66 of a 95 ms render for the
    40-part demo satellite); the output is identical. ``call.frozen``: the frozen function."""
    import drjit as dr
    import mitsuba as mi

    @dr.freeze(warn_after=RECORDINGS_PER_SENSOR * sensors)
    def render(scene: object, sensor: int, spp: int, seed: object) -> object:
        return mi.render(scene, sensor=sensor, spp=spp, seed=seed)

    def call(scene: object, sensor: int, spp: int, seed: int) -> object:
        return render(scene, sensor, spp, dr.opaque(mi.UInt32, seed))

    call.frozen = render  # type: ignore[attr-defined]
    return call
