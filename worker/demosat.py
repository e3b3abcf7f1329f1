"""Procedurally generated, textured demo satellite (the quick-start target).

Model frame (metres): origin at the centre of the bus, +Z along the bus long axis, +Y along the
solar array wings. The geometry is the same for every seed; the seed only drives the textures.
Textures are drawn so that a directional light reveals many distinct, non-periodic features
(foil wrinkles, labels, bolts, irregular solar cells), which the pose estimator tracks.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import pathlib
import tempfile

import cv2
import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from PIL import Image
from trimesh.exchange.gltf import export_glb
from trimesh.visual import TextureVisuals
from trimesh.visual.material import PBRMaterial

DEMO_MODEL_ID = "demo-sat"
DEMO_MODEL_NAME = "Demo satellite (procedural)"
DEMO_FILE_NAME = "demo-sat-v1.glb"

Parts = tuple[NDArray, NDArray, NDArray, NDArray]  # vertices, faces, normals, uv
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


# ----------------------------------------------------------------------------- textures
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


def _mli(rng: np.random.Generator, size: int, rects: dict[str, Rect]) -> NDArray:
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


def _solar(rng: np.random.Generator, w: int = 1024, hf: int = 820, h: int = 1024) -> NDArray:
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


def _dish(rng: np.random.Generator, size: int = 512) -> NDArray:
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


def _part(
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


# ----------------------------------------------------------------------------- geometry
_FACES = {
    "+x": ((1, 0, 0), (0, 0, 1)),
    "-x": ((-1, 0, 0), (0, 0, 1)),
    "+y": ((0, 1, 0), (0, 0, 1)),
    "-y": ((0, -1, 0), (0, 0, 1)),
    "+z": ((0, 0, 1), (0, 1, 0)),
    "-z": ((0, 0, -1), (0, 1, 0)),
}
_GRID6: dict[str, Rect] = {
    k: ((i % 3) / 3, (i // 3) / 2, (i % 3 + 1) / 3, (i // 3 + 1) / 2) for i, k in enumerate(_FACES)
}


def _box(extents: ArrayLike, rects: dict[str, Rect] | None = None) -> Parts:
    """Flat-shaded box centred at the origin; each face maps upright onto its own texture rect."""
    half = np.asarray(extents, float) / 2
    rects = rects or _GRID6
    ab = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    V, F, N, UV = [], [], [], []
    for k, (key, (n, v)) in enumerate(_FACES.items()):
        n, v = np.array(n, float), np.array(v, float)
        u = np.cross(v, n)  # (u, v, n) right-handed: the texture is not mirrored
        V.append(n * half + ab[:, :1] * u * half + ab[:, 1:] * v * half)
        N.append(np.tile(n, (4, 1)))
        x0, y0, x1, y1 = rects[key]
        x, y = x0 + (ab[:, 0] + 1) / 2 * (x1 - x0), y1 - (ab[:, 1] + 1) / 2 * (y1 - y0)
        UV.append(np.stack([x, 1 - y], 1))
        F.append(4 * k + np.array([[0, 1, 2], [0, 2, 3]]))
    return np.vstack(V), np.vstack(F), np.vstack(N), np.vstack(UV)


def _revolve(profile: list[ArrayLike], sections: int = 48) -> Parts:
    """Surface of revolution about +Z from (r, z) polylines; a crease between polylines.

    Traverse the profile counter-clockwise in the (r, z) plane so that normals point outwards.
    UVs: u around the axis, v along the profile arc length.
    """
    th = np.linspace(0, 2 * np.pi, sections + 1)
    segs = [np.asarray(p, float) for p in profile]
    arcs = [np.r_[0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))] for p in segs]
    offs = np.cumsum([0.0] + [a[-1] for a in arcs])
    V, F, N, UV, base = [], [], [], [], 0
    for p, arc, off in zip(segs, arcs, offs, strict=False):
        t = np.gradient(p, axis=0)
        nrz = np.stack([t[:, 1], -t[:, 0]], 1) / np.linalg.norm(t, axis=1, keepdims=True)
        for q, out in ((p, V), (nrz, N)):
            out.append(
                np.stack(
                    [
                        np.outer(q[:, 0], np.cos(th)),
                        np.outer(q[:, 0], np.sin(th)),
                        np.repeat(q[:, 1:], sections + 1, 1),
                    ],
                    -1,
                ).reshape(-1, 3)
            )
        uu, vv = np.meshgrid(th / (2 * np.pi), (off + arc) / offs[-1])
        UV.append(np.stack([uu, vv], -1).reshape(-1, 2))
        i, j = np.meshgrid(np.arange(len(p) - 1), np.arange(sections), indexing="ij")
        a = (base + i * (sections + 1) + j).ravel()
        c = a + sections + 1
        F.append(np.concatenate([np.stack([a, a + 1, c + 1], 1), np.stack([a, c + 1, c], 1)]))
        base += len(p) * (sections + 1)
    V, F, N, UV = np.vstack(V), np.vstack(F), np.vstack(N), np.vstack(UV)
    cross = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.einsum("ij,ij->i", cross, N[F].sum(1)) < 0
    F[flip] = F[flip][:, ::-1]
    return V, F[np.linalg.norm(cross, axis=1) > 1e-12], N, UV


def _cylinder(r: float, h: float, r_top: float | None = None, sections: int = 32) -> Parts:
    """Closed cylinder or truncated cone on +Z from z=0 (radius r) to z=h (radius r_top)."""
    rt = r if r_top is None else r_top
    return _revolve([[(0, 0), (r, 0)], [(r, 0), (rt, h)], [(rt, h), (0, h)]], sections)


def _tf(t: ArrayLike = (0, 0, 0), axis: ArrayLike = (1, 0, 0), deg: float = 0.0) -> NDArray:
    """Rigid transform: rotate by ``deg`` about ``axis``, then translate by ``t``."""
    T = trimesh.transformations.rotation_matrix(np.radians(deg), axis)
    T[:3, 3] = t
    return T


def _mesh(
    parts: Parts, tex: NDArray, name: str, metallic: float = 0.0, roughness: float = 0.7
) -> trimesh.Trimesh:
    """Textured, unprocessed mesh (vertices stay unshared, so box normals are face normals)."""
    v, f, n, uv = parts
    mat = PBRMaterial(
        name=name,
        baseColorTexture=Image.fromarray(tex, "RGB"),
        metallicFactor=metallic,
        roughnessFactor=roughness,
    )
    return trimesh.Trimesh(
        v, f, vertex_normals=n, visual=TextureVisuals(uv=uv, material=mat), process=False
    )


# ----------------------------------------------------------------------------- public API
def build_demo_satellite(seed: int = 0) -> trimesh.Scene:
    """Build the demo satellite as a scene graph of separately textured meshes.

    Parameters
    ----------
    seed : int
        Non-negative seed of the texture generator; the geometry does not depend on it.

    Returns
    -------
    trimesh.Scene
        About 12k triangles in some 40 nodes, nearly all with non-identity transforms (nested
        up to three deep; thrusters, hinges and struts are instances of one mesh each), every
        mesh with UVs and its own PBR material with a base colour texture.
    """
    rngs = (np.random.default_rng([seed, k]) for k in itertools.count())
    scene = trimesh.Scene()

    def add(
        name: str,
        parent: str,
        T: NDArray,
        parts: Parts | None = None,
        tex: NDArray | None = None,
        metal: float = 0.0,
        rough: float = 0.7,
        inst: str | None = None,
    ) -> None:
        if parts is not None and tex is not None:
            scene.add_geometry(
                _mesh(parts, tex, name, metal, rough),
                node_name=name,
                geom_name=name,
                parent_node_name=parent,
                transform=T,
            )
        else:  # a bare frame, or an instance of an existing geometry
            kw = {} if inst is None else {"geometry": inst}
            scene.graph.update(frame_to=name, frame_from=parent, matrix=T, **kw)

    def part(base: tuple[int, int, int], stripes: bool = False, size: int = 256) -> NDArray:
        return _part(next(rngs), base, size, stripes)

    # bus 2 x 2 x 3 m: the atlas gives every face its own region (170 px/m)
    rects = {
        "+x": (0, 0, 340, 510),
        "-x": (0, 510, 340, 1020),
        "+y": (340, 0, 680, 510),
        "-y": (340, 510, 680, 1020),
        "+z": (680, 0, 1020, 340),
        "-z": (680, 340, 1020, 680),
    }
    rects = {k: tuple(c / 1024 for c in r) for k, r in rects.items()}
    add(
        "bus",
        scene.graph.base_frame,
        _tf(),
        _box((2.0, 2.0, 3.0), rects),
        _mli(next(rngs), 1024, rects),
        0.0,
        0.55,
    )
    ring = [
        [(0.5, 0), (0.62, 0)],
        [(0.62, 0), (0.62, 0.12)],
        [(0.62, 0.12), (0.5, 0.12)],
        [(0.5, 0.12), (0.5, 0)],
    ]
    add(
        "launch_adapter",
        "bus",
        _tf((0, 0, -1.62)),
        _revolve(ring, 64),
        part((150, 150, 155), True),
        0.3,
        0.5,
    )
    for k, (x, y) in enumerate(((0.8, 0.8), (-0.8, 0.8), (-0.8, -0.8), (0.8, -0.8))):
        T = _tf((x, y, -1.5), (1, 0, 0), 180) @ _tf(axis=(-y, x, 0), deg=12)
        if k == 0:
            add(
                "thruster_0",
                "bus",
                T,
                _cylinder(0.03, 0.18, 0.085),
                part((90, 85, 80), True),
                0.5,
                0.4,
            )
        else:
            add(f"thruster_{k}", "bus", T, inst="thruster_0")
    for k, (pos, yaw) in enumerate((((0.45, 0.5, 1.59), 20), ((0.45, -0.35, 1.59), -70))):
        add(
            f"star_tracker_{k}",
            "bus",
            _tf(pos, (0, 0, 1), yaw),
            _box((0.24, 0.2, 0.18)),
            part((40, 40, 45)),
            0.0,
            0.6,
        )
        add(
            f"star_tracker_{k}_baffle",
            f"star_tracker_{k}",
            _tf((0.03, 0, 0.07), (0, 1, 0), 28),
            _cylinder(0.07, 0.22, 0.1),
            part((30, 30, 32), True),
            0.0,
            0.8,
        )
    for k, (ext, pos, col) in enumerate(
        (
            ((0.08, 0.6, 0.45), (-1.04, 0.3, 0.6), 225),
            ((0.1, 0.4, 0.7), (-1.05, -0.45, -0.5), 55),
            ((0.5, 0.08, 0.3), (-0.4, 1.04, -1.1), 215),
        )
    ):
        add(f"box_{k}", "bus", _tf(pos), _box(ext), part((col, col, col + 3)), 0.0, 0.7)
    add(
        "omni_antenna",
        "bus",
        _tf((-0.6, -0.6, 1.5), (1, 1, 0), 10),
        _cylinder(0.02, 0.5),
        part((230, 230, 230), True, 128),
        0.0,
        0.6,
    )

    # solar array wings on +-Y: yoke, then 3 panels 2.0 x 1.6 m (3 cm thick) with cells on +X
    prects = {"+x": (0, 0, 1, 0.8), "-x": (0, 0.8, 1, 1)} | dict.fromkeys(
        ("+y", "-y", "+z", "-z"), (0, 0, 1, 0.012)
    )
    for side, flip, tilt in (("py", 0, 18.0), ("my", 180, -25.0)):
        wing, sign = f"wing_{side}", 1 if flip == 0 else -1
        add(wing, "bus", _tf((0, sign, 0.25), (1, 0, 0), flip) @ _tf(axis=(0, 1, 0), deg=tilt))
        add(
            f"yoke_{side}",
            wing,
            _tf(axis=(1, 0, 0), deg=-90),
            _cylinder(0.04, 0.9, sections=24),
            part((160, 160, 165), True),
            0.3,
            0.5,
        )
        for k in range(3):
            add(
                f"panel_{side}_{k}",
                wing,
                _tf((0, 1.95 + 2.05 * k, 0)),
                _box((0.03, 2.0, 1.6), prects),
                _solar(next(rngs)),
                0.0,
                0.45,
            )
            for ab, z in (("a", -0.55), ("b", 0.5)):
                name, T = f"hinge_{side}_{k}{ab}", _tf((0, 0.925 + 2.05 * k, z))
                if name == "hinge_py_0a":
                    add(name, wing, T, _box((0.05, 0.06, 0.12)), part((120, 120, 125)), 0.4)
                else:
                    add(name, wing, T, inst="hinge_py_0a")

    # high-gain antenna: boom on +X, tilted paraboloid dish (D = 1.2 m, f = 0.45 m), feed, struts
    R, f, t = 0.6, 0.45, 0.025
    add(
        "hga_boom",
        "bus",
        _tf((1.0, 0, 0.8), (0, 1, 0), 90),
        _cylinder(0.05, 0.75, sections=24),
        part((170, 170, 170), True),
        0.3,
        0.5,
    )
    r = np.linspace(0, R, 28)
    back, front = np.stack([r, r**2 / (4 * f) - t], 1), np.stack([r, r**2 / (4 * f)], 1)[::-1]
    v, fc, n, _ = _revolve([back, [back[-1], front[0]], front], 96)
    uv = 0.5 + v[:, :2] * (0.49 / R, -0.49 / R)  # planar: rings stay rings
    add(
        "hga_dish",
        "hga_boom",
        _tf((0, 0, 0.75 + t), (1, 0, 0), -35) @ _tf(axis=(0, 0, 1), deg=15),
        (v, fc, n, uv),
        _dish(next(rngs)),
        0.0,
        0.6,
    )
    add(
        "hga_feed",
        "hga_dish",
        _tf((0, 0, f + 0.16), (1, 0, 0), 180),
        _cylinder(0.025, 0.16, 0.07),
        part((200, 200, 195)),
        0.2,
        0.5,
    )
    tip, foot = np.array([0, 0, f + 0.12]), np.array([0.95 * R, 0, (0.95 * R) ** 2 / (4 * f)])
    strut = trimesh.geometry.align_vectors((0, 0, 1), tip - foot)
    strut[:3, 3] = foot
    add(
        "hga_strut_0",
        "hga_dish",
        strut,
        _cylinder(0.012, float(np.linalg.norm(tip - foot)), sections=12),
        part((210, 210, 210), True, 128),
        0.0,
        0.6,
    )
    for k in (1, 2):
        add(
            f"hga_strut_{k}",
            "hga_dish",
            _tf(axis=(0, 0, 1), deg=120 * k) @ strut,
            inst="hga_strut_0",
        )
    return scene


def write_demo_satellite(path: pathlib.Path, seed: int = 0) -> pathlib.Path:
    """Export the demo satellite as a binary glTF (GLB), atomically and byte-deterministically.

    Parameters
    ----------
    path : pathlib.Path
        Destination file; parent directories are created. The file is written to a temporary
        file in the same directory and moved into place, so readers never see a partial file.
    seed : int
        Texture seed, see :func:`build_demo_satellite`.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = export_glb(build_demo_satellite(seed), include_normals=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def demo_satellite_path(data_dir: pathlib.Path) -> pathlib.Path:
    """Path of the demo satellite GLB under ``data_dir/models``, written first if missing.

    Parameters
    ----------
    data_dir : pathlib.Path
        The service data directory.

    Returns
    -------
    pathlib.Path
        ``data_dir / "models" / "demo-sat-v1.glb"``.
    """
    path = pathlib.Path(data_dir) / "models" / DEMO_FILE_NAME
    if not path.is_file():
        write_demo_satellite(path)
    return path
