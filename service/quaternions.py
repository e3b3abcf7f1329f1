"""Unit quaternions [w, x, y, z] in plain Python, for the API process (which carries no numpy
code paths of its own): the page framing's view and the load test's initial guesses."""

from __future__ import annotations

import math

Quaternion = tuple[float, float, float, float]
Vector3 = tuple[float, float, float]


def axis_quaternion(axis: Vector3, angle_deg: float) -> Quaternion:
    """Unit quaternion of the active rotation by ``angle_deg`` about unit ``axis``."""
    half = math.radians(angle_deg) / 2.0
    s = math.sin(half)
    return (math.cos(half), axis[0] * s, axis[1] * s, axis[2] * s)


def multiply(a: Quaternion, b: Quaternion) -> Quaternion:
    """Hamilton product a ⊗ b: the rotation b, then a."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def rotate(q: Quaternion, v: Vector3) -> Vector3:
    """R(q) v, as q ⊗ [0, v] ⊗ q*."""
    w, x, y, z = multiply(multiply(q, (0.0, *v)), (q[0], -q[1], -q[2], -q[3]))
    return (x, y, z)
