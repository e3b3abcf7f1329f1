"""An independent reference renderer for the robustness suite: Mitsuba only finds which surface
each ray hits; the shading, the pixel filter and the antialiasing are our own, in numpy.

The estimator renders with Mitsuba's direct integrator, a box pixel filter, multi-jittered
samples, a Lambertian BRDF, the model file's smooth normals and textures prefiltered to the
working range. This renderer differs in each of those on purpose: jittered supersampling on an
F×F grid per pixel, the unfiltered texture (a camera sees the surface's full detail), flat
(faceted) or smooth shading normals, a BRDF of a class the estimator does not have (Lambert,
a Lommel–Seeliger mix for regolith, Oren–Nayar for rough diffuse, Blinn–Phong for glossy
spacecraft surfaces), a shadow ray to the sun, and a box or Gaussian pixel filter applied to the
supersampled image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel
from worker.engine.rays import drjit_floats, numpy_vectors
from worker.engine.renderer import LightingSpec, Renderer

Array = NDArray[np.float64]
#: Rays intersected per batch (memory).
RAY_CHUNK = 1 << 20
#: Lommel–Seeliger weight of the regolith law (the rest is Lambert), and its normalisation.
LOMMEL_WEIGHT = 0.7
#: Ray origins of shadow rays move off the surface by this fraction of the model radius.
SHADOW_EPSILON = 1e-4


@dataclass(frozen=True)
class Physics:
    """How the reference is shaded and sampled."""

    normals: str = "smooth"  # smooth (the file's vertex normals) | faceted
    brdf: str = "lambert"  # lambert | lommel | oren | phong
    roughness_deg: float = 25.0  # Oren–Nayar σ
    specular: float = 0.3  # Blinn–Phong share of the reflected light
    shininess: float = 30.0
    supersample: int = 4  # F: F×F jittered rays per pixel
    pixel_filter: str = "box"  # box | gaussian (σ = 0.5 px)


@dataclass
class _Hits:
    valid: NDArray[np.bool_]
    p: Array  # (n, 3) points, model frame
    n_geo: Array  # (n, 3) geometric (face) normals
    n_shade: Array  # (n, 3) shading normals (interpolated where the mesh has them)
    albedo: Array  # (n, 3) linear reflectance (texture, vertex colour or constant)


def _rays(origins: Array, dirs: Array) -> object:
    import mitsuba as mi

    o = drjit_floats(np.broadcast_to(origins, dirs.shape))
    return mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*drjit_floats(dirs)))


def _intersect(scene: object, origin: Array, dirs: Array) -> _Hits:
    import drjit as dr

    si = scene.ray_intersect(_rays(origin, dirs))  # type: ignore[attr-defined]
    valid, albedo = si.is_valid(), si.bsdf().eval_diffuse_reflectance(si)
    dr.eval(valid, si.p, si.n, si.sh_frame.n, albedo)  # one kernel: each read alone traced again
    return _Hits(
        valid=np.array(valid, dtype=bool),
        p=numpy_vectors(si.p),
        n_geo=numpy_vectors(si.n),
        n_shade=numpy_vectors(si.sh_frame.n),
        albedo=numpy_vectors(albedo),
    )


def _occluded(scene: object, points: Array, L: Array) -> NDArray[np.bool_]:
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    dirs = np.broadcast_to(L, points.shape)
    return np.array(scene.ray_test(_rays(points, dirs)), dtype=bool)  # type: ignore[attr-defined]


def _toward(n: Array, v: Array) -> Array:
    """``n`` flipped where it faces away from ``v`` (surfaces are two-sided)."""
    return np.where((np.einsum("ij,ij->i", n, v) < 0)[:, None], -n, n)


def _reflectance(phys: Physics, n: Array, L: Array, V: Array) -> Array:
    """BRDF × cos θ_i per ray, for unit normal n, light L and view V (towards the camera)."""
    mu0 = np.clip(n @ L, 0.0, None)
    mu = np.clip(np.einsum("ij,ij->i", n, V), 1e-4, None)
    if phys.brdf == "lambert":
        return mu0 / np.pi
    if phys.brdf == "lommel":
        lommel = mu0 / np.maximum(mu0 + mu, 1e-6)
        return (LOMMEL_WEIGHT * lommel + (1.0 - LOMMEL_WEIGHT) * mu0) / np.pi
    if phys.brdf == "oren":
        s2 = np.radians(phys.roughness_deg) ** 2
        A, B = 1.0 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)
        ti, tr = np.arccos(np.clip(mu0, 0, 1)), np.arccos(np.clip(mu, 0, 1))
        li, lr = L[None] - mu0[:, None] * n, V - mu[:, None] * n
        cos_phi = np.einsum("ij,ij->i", li, lr) / np.maximum(
            np.linalg.norm(li, axis=1) * np.linalg.norm(lr, axis=1), 1e-9
        )
        alpha, beta = np.maximum(ti, tr), np.minimum(ti, tr)
        return mu0 / np.pi * (A + B * np.clip(cos_phi, 0, None) * np.sin(alpha) * np.tan(beta))
    if phys.brdf == "phong":
        h = L[None] + V
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        nh = np.clip(np.einsum("ij,ij->i", n, h), 0.0, None)
        lobe = (phys.shininess + 2.0) / (2.0 * np.pi) * nh**phys.shininess
        return (1.0 - phys.specular) * mu0 / np.pi + phys.specular * lobe * mu0
    raise ValueError(f"unknown BRDF {phys.brdf!r}")


class RayTracer:
    """Renders one model through one camera; ``render`` takes the pose, sun and physics."""

    def __init__(self, model: LoadedModel, camera: PinholeCamera) -> None:
        self.model, self.camera = model, camera
        # Only the scene's geometry and materials are used (unfiltered textures).
        dark = LightingSpec((0.0, 0.0, -1.0), 1.0, 0.0)
        self._scene = Renderer(model, camera, dark, spp=1, px_per_unit=None).scene

    def _subpixel_rays(self, phys: Physics, pad: int, rng: np.random.Generator) -> Array:
        F, cam = phys.supersample, self.camera
        us = np.arange(-pad * F, (cam.width + pad) * F)
        vs = np.arange(-pad * F, (cam.height + pad) * F)
        U, V = np.meshgrid(us, vs)
        u = (U + rng.uniform(0.0, 1.0, U.shape)) / F - 0.5
        v = (V + rng.uniform(0.0, 1.0, V.shape)) / F - 0.5
        return cam.rays(np.column_stack([u.ravel(), v.ravel()]))

    def render(
        self,
        R: Array,
        t: Array,
        sun_cam: Array,
        irradiance: float,
        ambient: float,
        phys: Physics,
        rng: np.random.Generator,
    ) -> NDArray[np.float32]:
        """Linear RGB (H, W, 3) of the model at pose b = R a + t, sun ``sun_cam`` (camera
        frame, towards the sun)."""
        pad = 2 if phys.pixel_filter == "gaussian" else 0
        dirs = self._subpixel_rays(phys, pad, rng) @ R  # Rᵀ d: model frame
        origin = -R.T @ t
        L = R.T @ np.asarray(sun_cam, dtype=np.float64)
        L /= np.linalg.norm(L)
        out = np.zeros((len(dirs), 3))
        for s in range(0, len(dirs), RAY_CHUNK):
            d = dirs[s : s + RAY_CHUNK]
            out[s : s + len(d)] = self._shade(d, origin, L, irradiance, ambient, phys)
        F, cam = phys.supersample, self.camera
        img = out.reshape((cam.height + 2 * pad) * F, (cam.width + 2 * pad) * F, 3)
        img = img.astype(np.float32)
        if phys.pixel_filter == "gaussian":
            img = cv2.GaussianBlur(img, (0, 0), 0.5 * F)
        h, w = img.shape[0] // F, img.shape[1] // F
        img = img.reshape(h, F, w, F, 3).mean(axis=(1, 3))
        return np.ascontiguousarray(img[pad : pad + cam.height, pad : pad + cam.width])

    def _shade(
        self,
        d: Array,
        origin: Array,
        L: Array,
        irradiance: float,
        ambient: float,
        phys: Physics,
    ) -> Array:
        hits = _intersect(self._scene, origin, d)
        out = np.zeros((len(d), 3))
        idx = np.flatnonzero(hits.valid)
        if len(idx) == 0:
            return out
        V = -d[idx]
        n_geo = _toward(hits.n_geo[idx], V)
        n = n_geo if phys.normals == "faceted" else _toward(hits.n_shade[idx], V)
        lit = n_geo @ L > 0.0
        cand = np.flatnonzero(lit)
        p = hits.p[idx][cand] + SHADOW_EPSILON * self.model.radius * n_geo[cand]
        lit[cand] &= ~_occluded(self._scene, p, L)
        rho = hits.albedo[idx]
        f = _reflectance(phys, n, L, V) * lit
        out[idx] = irradiance * rho * f[:, None] + ambient * rho
        return out
