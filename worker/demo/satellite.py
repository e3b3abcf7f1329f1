"""Procedurally generated, textured demo satellite (the quick-start target).

Model frame (metres): origin at the centre of the bus, +Z along the bus long axis, +Y along the
solar array wings. The geometry is the same for every seed; the seed only drives the textures.
Textures are drawn so that a directional light reveals many distinct, non-periodic features
(foil wrinkles, labels, bolts, irregular solar cells), which the pose estimator tracks.
"""

from __future__ import annotations

import itertools
import pathlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from worker.demo.geometry import Parts, box, cylinder, revolve, textured_mesh, tf, write_glb
from worker.demo.textures import dish_texture, mli_texture, part_texture, solar_texture

DEMO_MODEL_NAME = "Demo satellite (procedural)"
DEMO_FILE_NAME = "demo-sat-v1.glb"


#: A texture drawn from its part's own seeded generator (see :func:`build_demo_satellite`).
Texture = Callable[[np.random.Generator], NDArray]


@dataclass(frozen=True)
class Part:
    """One node of the satellite: a textured mesh, an instance of an earlier one, or a frame.

    ``T`` places the node in its parent's frame (None as parent: the scene's base frame).
    """

    name: str
    parent: str | None
    T: NDArray
    mesh: Parts | None = None
    texture: Texture | None = None
    metal: float = 0.0
    rough: float = 0.7
    instance_of: str | None = None


def painted(base: tuple[int, int, int], stripes: bool = False, size: int = 256) -> Texture:
    """The texture of a small part (see :func:`worker.demo.textures.part_texture`)."""
    return lambda rng: part_texture(rng, base, size, stripes)


#: Texture atlas of the bus (2 × 2 × 3 m): every face its own region, 170 px/m, in fractions.
BUS_RECTS = {
    k: tuple(c / 1024 for c in r)
    for k, r in {
        "+x": (0, 0, 340, 510),
        "-x": (0, 510, 340, 1020),
        "+y": (340, 0, 680, 510),
        "-y": (340, 510, 680, 1020),
        "+z": (680, 0, 1020, 340),
        "-z": (680, 340, 1020, 680),
    }.items()
}
#: Solar panels: cells on +X, the back on -X, thin edges.
PANEL_RECTS = {"+x": (0, 0, 1, 0.8), "-x": (0, 0.8, 1, 1)} | dict.fromkeys(
    ("+y", "-y", "+z", "-z"), (0, 0, 1, 0.012)
)


def bus_parts() -> list[Part]:
    """The bus (2 × 2 × 3 m) with its launch adapter and four thrusters."""
    ring = [
        [(0.5, 0), (0.62, 0)],
        [(0.62, 0), (0.62, 0.12)],
        [(0.62, 0.12), (0.5, 0.12)],
        [(0.5, 0.12), (0.5, 0)],
    ]
    thrusters = [
        tf((x, y, -1.5), (1, 0, 0), 180) @ tf(axis=(-y, x, 0), deg=12)
        for x, y in ((0.8, 0.8), (-0.8, 0.8), (-0.8, -0.8), (0.8, -0.8))
    ]
    return [
        Part(
            "bus",
            None,
            tf(),
            box((2.0, 2.0, 3.0), BUS_RECTS),
            lambda rng: mli_texture(rng, 1024, BUS_RECTS),
            0.0,
            0.55,
        ),
        Part(
            "launch_adapter",
            "bus",
            tf((0, 0, -1.62)),
            revolve(ring, 64),
            painted((150, 150, 155), True),
            0.3,
            0.5,
        ),
        Part(
            "thruster_0",
            "bus",
            thrusters[0],
            cylinder(0.03, 0.18, 0.085),
            painted((90, 85, 80), True),
            0.5,
            0.4,
        ),
        *(Part(f"thruster_{k}", "bus", thrusters[k], instance_of="thruster_0") for k in (1, 2, 3)),
    ]


def equipment_parts() -> list[Part]:
    """What sits on the bus: two star trackers with baffles, three boxes, the omni antenna."""
    parts = []
    for k, (pos, yaw) in enumerate((((0.45, 0.5, 1.59), 20), ((0.45, -0.35, 1.59), -70))):
        parts += [
            Part(
                f"star_tracker_{k}",
                "bus",
                tf(pos, (0, 0, 1), yaw),
                box((0.24, 0.2, 0.18)),
                painted((40, 40, 45)),
                0.0,
                0.6,
            ),
            Part(
                f"star_tracker_{k}_baffle",
                f"star_tracker_{k}",
                tf((0.03, 0, 0.07), (0, 1, 0), 28),
                cylinder(0.07, 0.22, 0.1),
                painted((30, 30, 32), True),
                0.0,
                0.8,
            ),
        ]
    for k, (ext, pos, col) in enumerate(
        (
            ((0.08, 0.6, 0.45), (-1.04, 0.3, 0.6), 225),
            ((0.1, 0.4, 0.7), (-1.05, -0.45, -0.5), 55),
            ((0.5, 0.08, 0.3), (-0.4, 1.04, -1.1), 215),
        )
    ):
        parts.append(Part(f"box_{k}", "bus", tf(pos), box(ext), painted((col, col, col + 3))))
    antenna = Part(
        "omni_antenna",
        "bus",
        tf((-0.6, -0.6, 1.5), (1, 1, 0), 10),
        cylinder(0.02, 0.5),
        painted((230, 230, 230), True, 128),
        0.0,
        0.6,
    )
    return [*parts, antenna]


def wing_parts(side: str, flip: float, tilt_deg: float) -> list[Part]:
    """A solar array wing on ±Y: a frame, the yoke, three 2.0 × 1.6 m panels with hinges."""
    wing, sign = f"wing_{side}", 1 if flip == 0 else -1
    T = tf((0, sign, 0.25), (1, 0, 0), flip) @ tf(axis=(0, 1, 0), deg=tilt_deg)
    parts = [
        Part(wing, "bus", T),
        Part(
            f"yoke_{side}",
            wing,
            tf(axis=(1, 0, 0), deg=-90),
            cylinder(0.04, 0.9, sections=24),
            painted((160, 160, 165), True),
            0.3,
            0.5,
        ),
    ]
    for k in range(3):
        parts.append(
            Part(
                f"panel_{side}_{k}",
                wing,
                tf((0, 1.95 + 2.05 * k, 0)),
                box((0.03, 2.0, 1.6), PANEL_RECTS),
                solar_texture,
                0.0,
                0.45,
            )
        )
        for ab, z in (("a", -0.55), ("b", 0.5)):
            name, T = f"hinge_{side}_{k}{ab}", tf((0, 0.925 + 2.05 * k, z))
            if name == "hinge_py_0a":
                parts.append(
                    Part(name, wing, T, box((0.05, 0.06, 0.12)), painted((120, 120, 125)), 0.4)
                )
            else:
                parts.append(Part(name, wing, T, instance_of="hinge_py_0a"))
    return parts


def antenna_parts() -> list[Part]:
    """The high-gain antenna: a boom on +X, a tilted paraboloid dish (D = 1.2 m, f = 0.45 m)
    with its feed and three struts."""
    R, f, t = 0.6, 0.45, 0.025
    r = np.linspace(0, R, 28)
    back, front = np.stack([r, r**2 / (4 * f) - t], 1), np.stack([r, r**2 / (4 * f)], 1)[::-1]
    v, fc, n, _ = revolve([back, [back[-1], front[0]], front], 96)
    uv = 0.5 + v[:, :2] * (0.49 / R, -0.49 / R)  # planar: rings stay rings
    tip, foot = np.array([0, 0, f + 0.12]), np.array([0.95 * R, 0, (0.95 * R) ** 2 / (4 * f)])
    strut = trimesh.geometry.align_vectors((0, 0, 1), tip - foot)
    strut[:3, 3] = foot
    dish_T = tf((0, 0, 0.75 + t), (1, 0, 0), -35) @ tf(axis=(0, 0, 1), deg=15)
    return [
        Part(
            "hga_boom",
            "bus",
            tf((1.0, 0, 0.8), (0, 1, 0), 90),
            cylinder(0.05, 0.75, sections=24),
            painted((170, 170, 170), True),
            0.3,
            0.5,
        ),
        Part("hga_dish", "hga_boom", dish_T, (v, fc, n, uv), dish_texture, 0.0, 0.6),
        Part(
            "hga_feed",
            "hga_dish",
            tf((0, 0, f + 0.16), (1, 0, 0), 180),
            cylinder(0.025, 0.16, 0.07),
            painted((200, 200, 195)),
            0.2,
            0.5,
        ),
        Part(
            "hga_strut_0",
            "hga_dish",
            strut,
            cylinder(0.012, float(np.linalg.norm(tip - foot)), sections=12),
            painted((210, 210, 210), True, 128),
            0.0,
            0.6,
        ),
        *(
            Part(
                f"hga_strut_{k}",
                "hga_dish",
                tf(axis=(0, 0, 1), deg=120 * k) @ strut,
                instance_of="hga_strut_0",
            )
            for k in (1, 2)
        ),
    ]


def satellite_parts() -> list[Part]:
    """Every node of the satellite, parents before children, in the order textures are drawn."""
    return [
        *bus_parts(),
        *equipment_parts(),
        *wing_parts("py", 0, 18.0),
        *wing_parts("my", 180, -25.0),
        *antenna_parts(),
    ]


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
        mesh with UVs and its own PBR material with a base colour texture. The k-th textured
        part of :func:`satellite_parts` draws its texture from generator ``[seed, k]``.
    """
    rngs = (np.random.default_rng([seed, k]) for k in itertools.count())
    scene = trimesh.Scene()
    for part in satellite_parts():
        parent = scene.graph.base_frame if part.parent is None else part.parent
        if part.mesh is not None and part.texture is not None:
            mesh = textured_mesh(
                part.mesh, part.texture(next(rngs)), part.name, part.metal, part.rough
            )
            scene.add_geometry(
                mesh,
                node_name=part.name,
                geom_name=part.name,
                parent_node_name=parent,
                transform=part.T,
            )
        else:  # a bare frame, or an instance of an existing geometry
            kw = {} if part.instance_of is None else {"geometry": part.instance_of}
            scene.graph.update(frame_to=part.name, frame_from=parent, matrix=part.T, **kw)
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
    return write_glb(path, build_demo_satellite(seed))


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
