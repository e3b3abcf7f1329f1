"""Procedural textures of the demo satellite: MLI foil, solar cells, dish and small parts.

Every texture is drawn from a seeded generator so that a directional light reveals many distinct,
non-periodic features (foil wrinkles, labels, bolts, irregular solar cells), which the pose
estimator tracks. Images are RGB ``uint8`` arrays of shape ``(h, w, 3)``.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

Rect = tuple[float, float, float, float]  # x0, y0, x1, y1 as fractions of the image, y down

_WORDS = (
    "HTR",
    "TC",
    "RAD",
    "J",
    "P",
    "MLI",
    "GND",
    "TX",
    "RX",
    "SA",
    "RBF",
    "NO STEP",
    "PYRO",
    "CAUTION",
    "ESD",
    "LOAD",
    "VENT",
    "DO NOT",
    "S/N",
    "CAL",
    "FWD",
    "AFT",
    "ZONE",
    "BIAS",
)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _upsample(g: NDArray, h: int, w: int) -> NDArray:
    """Smooth (smoothstep-weighted bilinear) resampling of a coarse grid to ``(h, w)``."""
    for axis, n in ((0, h), (1, w)):
        m = g.shape[axis]
        x = (np.arange(n) + 0.5) * (m - 1) / n
        i = np.minimum(np.floor(x).astype(int), m - 2)
        f = x - i
        f = f * f * (3.0 - 2.0 * f)
        f = f[:, None] if axis == 0 else f[None, :]
        a, b = np.take(g, i, axis=axis), np.take(g, i + 1, axis=axis)
        g = a * (1.0 - f) + b * f
    return g


def _noise(
    rng: np.random.Generator, h: int, w: int, cell: float, octaves: int = 4, stretch: float = 1.0
) -> NDArray:
    """Fractal value noise, zero mean and unit standard deviation, shape ``(h, w)``.

    ``cell`` is the coarsest feature size in pixels; ``stretch`` > 1 elongates features along x.
    """
    out = np.zeros((h, w))
    for o in range(octaves):
        c = cell / 2**o
        g = rng.standard_normal((int(h / c) + 2, int(w / (c * stretch)) + 2))
        out += _upsample(g, h, w) * 0.55**o
    return (out - out.mean()) / (out.std() + 1e-12)


def _label(img: NDArray, rng: np.random.Generator, x: int, y: int, scale: float = 0.45) -> None:
    """Draw a white-on-black or black-on-white text label with its top-left corner at (x, y)."""
    lines = [
        f"{_WORDS[rng.integers(len(_WORDS))]} {rng.integers(1, 99):02d}"
        f"{'ABCDEFXYZ'[rng.integers(9)]}"
        for _ in range(int(rng.integers(1, 3)))
    ]
    th = int(22 * scale / 0.45)
    w = max(cv2.getTextSize(t, _FONT, scale, 1)[0][0] for t in lines) + 8
    bg, fg = ((245, 245, 240), (15, 15, 15)) if rng.random() < 0.6 else ((20, 20, 22), (235,) * 3)
    cv2.rectangle(img, (x, y), (x + w, y + th * len(lines) + 4), bg, -1)
    cv2.rectangle(img, (x, y), (x + w, y + th * len(lines) + 4), (60, 60, 60), 1)
    for k, t in enumerate(lines):
        cv2.putText(img, t, (x + 4, y + th * (k + 1) - 3), _FONT, scale, fg, 1, cv2.LINE_AA)


def _bolts(
    img: NDArray, rng: np.random.Generator, x0: int, y0: int, x1: int, y1: int, step: float
) -> None:
    """Dark bolt heads along the border of a rectangle, irregularly spaced."""
    corners = np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], float)
    for a, b in zip(corners, np.roll(corners, -1, 0), strict=True):
        for t in np.sort(rng.uniform(0, 1, max(1, int(np.linalg.norm(b - a) / step)))):
            c = tuple(int(v) for v in a + t * (b - a))
            cv2.circle(img, c, int(rng.integers(2, 4)), (35, 35, 40), -1, cv2.LINE_AA)


def _walk(rng: np.random.Generator, x: float, y: float, n: int, step: float) -> NDArray:
    """Random polyline (a crease, scratch or harness) starting at (x, y)."""
    ang = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.6, n))
    lens = rng.uniform(0.3, 1.0, n) * step
    pts = np.cumsum(np.stack([lens * np.cos(ang), lens * np.sin(ang)], 1), 0) + (x, y)
    return np.vstack([(x, y), pts]).astype(np.int32)


def mli_texture(rng: np.random.Generator, size: int, rects: dict[str, Rect]) -> NDArray:
    """Gold multi-layer-insulation foil atlas with creases, tape, labels and radiators."""
    n = np.abs(_noise(rng, size, size, 60, 4, 2.5)) + 0.7 * np.abs(_noise(rng, size, size, 45, 3))
    gy, gx = np.gradient(-n)
    g = 0.8 * gx + 0.6 * gy
    shade = np.clip(0.5 + 0.2 * g / g.std() + 0.12 * _noise(rng, size, size, 120), 0, 1)
    dark, mid, lit = np.array([70, 40, 8]), np.array([200, 140, 45]), np.array([255, 235, 160])
    s = shade[..., None]
    img = np.where(s < 0.5, dark + (mid - dark) * 2 * s, mid + (lit - mid) * (2 * s - 1))
    img = np.ascontiguousarray(img.astype(np.uint8))
    for x0, y0, x1, y1 in (np.array(r) * size for r in rects.values()):
        x0, y0, x1, y1 = int(x0), int(y0), int(x1), int(y1)
        w, h = x1 - x0, y1 - y0
        for _ in range(w * h // 4500):  # creases: a dark fold with a bright lip
            p = _walk(rng, rng.uniform(x0, x1), rng.uniform(y0, y1), int(rng.integers(3, 9)), 50)
            cv2.polylines(img, [p], False, (60, 35, 5), 2, cv2.LINE_AA)
            cv2.polylines(img, [p + 2], False, (255, 240, 180), 1, cv2.LINE_AA)
        for _ in range(int(rng.integers(2, 4))):  # tape seams across the face
            t, vert = int(rng.integers(8, 16)), rng.random() < 0.5
            col = ((190, 190, 185), (150, 95, 20))[rng.integers(2)]
            a = int(rng.uniform(10, (w if vert else h) - 25))
            p0, p1 = ((x0 + a, y0), (x0 + a + t, y1)) if vert else ((x0, y0 + a), (x1, y0 + a + t))
            cv2.rectangle(img, p0, p1, col, -1)
            cv2.rectangle(img, p0, p1, (40, 30, 10), 1)
        if rng.random() < 0.75:  # radiator: white panel with an irregular grid and bolts
            rw, rh = int(w * rng.uniform(0.3, 0.55)), int(h * rng.uniform(0.25, 0.45))
            rx, ry = int(rng.uniform(x0 + 8, x1 - rw - 8)), int(rng.uniform(y0 + 8, y1 - rh - 8))
            cv2.rectangle(img, (rx, ry), (rx + rw, ry + rh), (238, 238, 232), -1)
            for gxp in np.sort(rng.uniform(rx, rx + rw, int(rng.integers(2, 6)))):
                cv2.line(img, (int(gxp), ry), (int(gxp), ry + rh), (150, 150, 155), 1)
            for gyp in np.sort(rng.uniform(ry, ry + rh, int(rng.integers(2, 6)))):
                cv2.line(img, (rx, int(gyp)), (rx + rw, int(gyp)), (150, 150, 155), 1)
            _bolts(img, rng, rx + 4, ry + 4, rx + rw - 4, ry + rh - 4, 22)
        for _ in range(int(rng.integers(3, 7))):
            _label(
                img,
                rng,
                int(rng.uniform(x0, x1 - 90)),
                int(rng.uniform(y0, y1 - 40)),
                float(rng.uniform(0.35, 0.55)),
            )
        for _ in range(int(rng.integers(4, 10))):  # connectors, sensors, velcro dots
            c = (int(rng.uniform(x0, x1)), int(rng.uniform(y0, y1)))
            r = int(rng.integers(3, 9))
            if rng.random() < 0.5:
                cv2.circle(img, c, r, (25, 25, 25), -1, cv2.LINE_AA)
            else:
                cv2.rectangle(img, c, (c[0] + 2 * r, c[1] + r), (25, 25, 25), -1)
    return img


def solar_texture(rng: np.random.Generator, w: int = 1024, hf: int = 820, h: int = 1024) -> NDArray:
    """Solar panel atlas: irregular cell field (rows < hf) above the panel back (rows >= hf)."""
    img = np.zeros((h, w, 3), np.uint8)
    frame, cols, rows, gap = 14, 16, 20, 3
    img[:hf] = (175, 175, 180)
    cw, ch = (w - 2 * frame) / cols, (hf - 2 * frame) / rows
    sheen = _noise(rng, hf, w, 300, 2)
    string_tint = rng.normal(0, 0.08, rows)
    for i in range(rows):
        for j in range(cols):
            x0, y0 = int(frame + j * cw + gap), int(frame + i * ch + gap)
            x1, y1 = int(frame + (j + 1) * cw - 1), int(frame + (i + 1) * ch - 1)
            u = rng.random()
            if u < 0.025:  # missing cell: Kapton substrate shows through
                img[y0:y1, x0:x1] = (150, 105, 40)
                continue
            lum = 1.0 + rng.normal(0, 0.22) + string_tint[i] + 0.12 * sheen[y0, x0]
            base = np.array([22, 34, 95]) * lum + rng.normal(0, 6, 3) * (1, 1, 2)
            if u < 0.06:  # dead / dark cell
                base = np.array([8, 9, 14]) + rng.normal(0, 2, 3)
            img[y0:y1, x0:x1] = np.clip(base, 0, 255).astype(np.uint8)
            finger = tuple(int(v) for v in np.clip(base * 1.5 + 25, 0, 255))
            for yy in range(y0 + 3 + int(rng.integers(3)), y1 - 1, 5):
                cv2.line(img, (x0, yy), (x1 - 1, yy), finger, 1)
            for f in (0.25, 0.75):
                xb = int(x0 + f * (x1 - x0) + rng.integers(-3, 4))
                cv2.rectangle(img, (xb, y0), (xb + 1, y1 - 1), (200, 200, 205), -1)
            if j < cols - 1:  # interconnects to the next cell, random count and position
                for _ in range(int(rng.integers(0, 4))):
                    yy = int(rng.uniform(y0 + 2, y1 - 5))
                    cv2.rectangle(img, (x1 - 3, yy), (x1 + gap + 3, yy + 3), (225, 225, 228), -1)
            if rng.random() < 0.04:  # bypass diode / repair mark
                cv2.rectangle(img, (x0 + 2, y0 + 2), (x0 + 9, y0 + 7), (240, 240, 240), -1)
    for _ in range(int(rng.integers(3, 7))):  # scratches and stains
        p = _walk(rng, rng.uniform(0, w), rng.uniform(0, hf), int(rng.integers(3, 7)), 70)
        cv2.polylines(img, [p], False, (150, 160, 190), 1, cv2.LINE_AA)
    for _ in range(40):  # frame markings: ticks, tie-down blocks, part numbers
        a = rng.uniform(0.01, 0.97)
        x, y = ((a * w, 2), (a * w, hf - 12), (2, a * hf), (w - 12, a * hf))[rng.integers(4)]
        cv2.rectangle(
            img, (int(x), int(y)), (int(x) + int(rng.integers(3, 25)), int(y) + 9), (20, 20, 20), -1
        )
    for x in rng.uniform(40, w - 200, 3):
        cv2.putText(
            img,
            f"SA-{int(rng.integers(1000, 9999))}",
            (int(x), 11),
            _FONT,
            0.35,
            (250, 250, 250),
            1,
            cv2.LINE_AA,
        )
    back = 200 + 18 * _noise(rng, h - hf, w, 40, 3)
    img[hf:] = np.clip(back, 0, 255)[..., None].astype(np.uint8)
    sub = img[hf:]
    for _ in range(14):  # harness runs and labels on the back
        p = _walk(rng, rng.uniform(0, w), rng.uniform(0, h - hf), 5, 90)
        cv2.polylines(sub, [p], False, (40, 40, 45), 3, cv2.LINE_AA)
    for _ in range(6):
        _label(sub, rng, int(rng.uniform(0, w - 100)), int(rng.uniform(0, h - hf - 40)), 0.4)
    return img


def dish_texture(rng: np.random.Generator, size: int = 512) -> NDArray:
    """Light grey dish with broken darker rings, patches, bolts and labels (planar UVs)."""
    img = np.clip(225 + 14 * _noise(rng, size, size, 80, 3), 0, 255)[..., None]
    img = np.ascontiguousarray(np.repeat(img, 3, 2).astype(np.uint8))
    c = size // 2
    for _ in range(7):
        r = int(rng.uniform(0.12, 0.48) * size)
        a0 = rng.uniform(0, 360)
        g = int(rng.integers(60, 170))
        cv2.ellipse(
            img,
            (c, c),
            (r, r),
            0,
            a0,
            a0 + rng.uniform(120, 330),
            (g, g, g + 8),
            int(rng.integers(2, 9)),
            cv2.LINE_AA,
        )
    for _ in range(9):
        p = rng.uniform(0.15, 0.85, 2) * size
        box = cv2.boxPoints(((p[0], p[1]), tuple(rng.uniform(12, 60, 2)), rng.uniform(0, 90)))
        g = int(rng.integers(40, 150))
        cv2.fillPoly(img, [box.astype(np.int32)], (g, g, g), cv2.LINE_AA)
    for a in np.sort(rng.uniform(0, 2 * np.pi, 11)):
        cv2.circle(img, (int(c + 40 * np.cos(a)), int(c + 40 * np.sin(a))), 4, (30,) * 3, -1)
    cv2.circle(img, (c, c), 22, (70, 70, 75), -1, cv2.LINE_AA)
    for _ in range(4):
        _label(img, rng, int(rng.uniform(60, size - 160)), int(rng.uniform(60, size - 100)))
    return img


def part_texture(
    rng: np.random.Generator, base: tuple[int, int, int], size: int = 256, stripes: bool = False
) -> NDArray:
    """Texture for a small part: painted base, irregular stripes or panels, bolts, a label."""
    img = np.array(base) + 12 * _noise(rng, size, size, 40, 3)[..., None]
    img = np.ascontiguousarray(np.clip(img, 0, 255).astype(np.uint8))
    dark = tuple(int(v * 0.2) for v in base)
    if stripes:  # stripes across the length (v), irregular widths and spacing
        for y in np.sort(rng.uniform(0, size, int(rng.integers(5, 10)))):
            cv2.rectangle(img, (0, int(y)), (size, int(y + rng.integers(4, 18))), dark, -1)
        cv2.line(img, (int(rng.uniform(0, size)), 0), (int(rng.uniform(0, size)), size), dark, 2)
    else:
        for _ in range(int(rng.integers(3, 7))):
            x, y = rng.integers(0, size - 30, 2)
            x2, y2 = x + rng.integers(15, 90), y + rng.integers(15, 90)
            col = tuple(int(v) for v in np.clip(np.array(base) * rng.uniform(0.3, 1.6), 0, 255))
            cv2.rectangle(img, (int(x), int(y)), (int(x2), int(y2)), col, -1)
            _bolts(img, rng, int(x) + 4, int(y) + 4, int(x2) - 4, int(y2) - 4, 16)
    _label(img, rng, int(rng.uniform(5, size - 110)), int(rng.uniform(5, size - 50)), 0.4)
    return img
