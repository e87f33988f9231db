"""An exact analytic ray tracer in numpy for the built-in synthetic scene (independent of our rasterizer).

Primitives are intersected in closed form (plane, sphere, oriented box), shading is Lambert with a directional
light, hard shadows and ambient, and albedo comes from procedural solid textures. Camera rays are built with
camera-z = 1, so the hit parameter t *is* the camera-space depth: depth maps are exact at pixel centres.
Colour is averaged over a few fixed sub-pixel rays (anti-aliasing); depth, normals and labels come from the
pixel-centre ray, so they are exact rather than blended.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from warpgs.data.camera import Camera

EPS = 1e-6
# Rotated-grid 4x supersampling pattern (sub-pixel offsets from the pixel centre).
SUBPIXEL_OFFSETS = ((-0.375, -0.125), (0.125, -0.375), (0.375, 0.125), (-0.125, 0.375))

Texture = Callable[[np.ndarray], np.ndarray]  # world points [N, 3] -> albedo [N, 3]


@dataclass
class Plane:
    """The horizontal square |x|, |y| <= half_extent at height z."""

    name: str
    z: float
    half_extent: float
    texture: Texture

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(divide="ignore", invalid="ignore"):  # rays parallel to the plane miss it
            t = (self.z - o[:, 2]) / d[:, 2]
            p = o + t[:, None] * d
            ok = (t > EPS) & (np.abs(p[:, 0]) <= self.half_extent) & (np.abs(p[:, 1]) <= self.half_extent)
        normal = np.zeros_like(o)
        normal[:, 2] = np.where(o[:, 2] >= self.z, 1.0, -1.0)  # face the viewer's side
        return np.where(ok, t, np.inf), normal


@dataclass
class Sphere:
    name: str
    center: Sequence[float]
    radius: float
    texture: Texture

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = _sphere_t(o, d, np.asarray(self.center, dtype=np.float64), self.radius)
        normal = np.zeros_like(o)
        hit = np.isfinite(t)
        normal[hit] = (o[hit] + t[hit, None] * d[hit] - np.asarray(self.center)) / self.radius
        return t, normal


def _sphere_t(o: np.ndarray, d: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Ray parameter of the nearer sphere intersection (inf on a miss); rays never start inside a sphere here."""
    oc = o - center
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - radius ** 2
    disc = b * b - a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc >= 0) & (t > EPS), t, np.inf)


@dataclass
class Box:
    """A box with half sizes `half`, rotated by `yaw` radians about the world z axis."""

    name: str
    center: Sequence[float]
    half: Sequence[float]
    yaw: float
    texture: Texture
    _rot: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        self._rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # local -> world

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.full(len(o), np.inf)
        normal = np.zeros_like(o)
        centre, half = np.asarray(self.center, dtype=np.float64), np.asarray(self.half, dtype=np.float64)
        # Slab test only for the rays that hit the bounding sphere: most rays miss a small box.
        cand = np.nonzero(np.isfinite(_sphere_t(o, d, centre, float(np.linalg.norm(half)) * 1.001)))[0]
        if len(cand) == 0:
            return t, normal
        lo = (o[cand] - centre) @ self._rot  # world -> local is R^T, applied to row vectors
        ld = d[cand] @ self._rot
        ld = np.where(np.abs(ld) < 1e-12, 1e-12, ld)
        t1, t2 = (-half - lo) / ld, (half - lo) / ld
        near, far = np.minimum(t1, t2), np.maximum(t1, t2)
        t_in, t_out = near.max(axis=1), far.min(axis=1)
        ok = (t_out >= t_in) & (t_in > EPS)
        rows = np.arange(len(cand))
        axis = near.argmax(axis=1)
        local_n = np.zeros_like(lo)
        local_n[rows, axis] = -np.sign(ld[rows, axis])
        t[cand] = np.where(ok, t_in, np.inf)
        normal[cand] = local_n @ self._rot.T
        return t, normal


@dataclass
class SceneDef:
    objects: list
    light_dir: Sequence[float] = (0.45, -0.35, 0.82)  # towards the light
    diffuse: float = 0.8
    ambient: float = 0.3
    sky_horizon: Sequence[float] = (0.86, 0.89, 0.93)
    sky_zenith: Sequence[float] = (0.50, 0.64, 0.86)

    @property
    def label_names(self) -> dict[int, str]:
        return {i + 1: obj.name for i, obj in enumerate(self.objects)}


def intersect(scene: SceneDef, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of each ray: (t [N] (inf on miss), unit normal [N, 3], object index [N] (-1 on miss))."""
    best_t = np.full(len(o), np.inf)
    normal = np.zeros_like(o)
    index = np.full(len(o), -1, dtype=np.int64)
    for k, obj in enumerate(scene.objects):
        t, n = obj.intersect(o, d)
        closer = t < best_t
        best_t = np.where(closer, t, best_t)
        normal[closer] = n[closer]
        index[closer] = k
    return best_t, normal, index


def shade(scene: SceneDef, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Radiance of each ray plus its hit data: (rgb [N, 3], t [N], normal [N, 3], object index [N])."""
    t, normal, index = intersect(scene, o, d)
    hit = index >= 0
    rgb = np.empty_like(o)
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    up = np.clip(unit[:, 2], 0.0, 1.0)[:, None]
    rgb[:] = (1 - up) * np.asarray(scene.sky_horizon) + up * np.asarray(scene.sky_zenith)
    if hit.any():
        p = o[hit] + t[hit, None] * d[hit]
        n = normal[hit]
        light = np.asarray(scene.light_dir, dtype=np.float64)
        light = light / np.linalg.norm(light)
        lit = np.maximum(n @ light, 0.0)
        shadow_t, _, _ = intersect(scene, p + 1e-4 * n, np.broadcast_to(light, p.shape).copy())
        lit = np.where(np.isfinite(shadow_t), 0.0, lit)
        albedo = np.zeros_like(p)
        for k, obj in enumerate(scene.objects):
            sel = index[hit] == k
            if sel.any():
                albedo[sel] = obj.texture(p[sel])
        rgb[hit] = albedo * (scene.ambient + scene.diffuse * lit[:, None])
    return np.clip(rgb, 0.0, 1.0), t, normal, index


def camera_rays(cam: Camera, offset: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-space origins and directions (camera z component 1) through every pixel centre + offset."""
    u, v = np.meshgrid(np.arange(cam.width) + 0.5 + offset[0], np.arange(cam.height) + 0.5 + offset[1])
    d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3)
    rot = cam.viewmat[:3, :3]
    d = d_cam @ rot  # camera -> world is R^T; for row vectors that is a right-multiplication by R
    return np.broadcast_to(cam.center, d.shape).copy(), d


@dataclass
class Rendering:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1], anti-aliased
    depth: np.ndarray  # [H, W] float32 camera z at the pixel centre; inf where the ray sees sky
    normal: np.ndarray  # [H, W, 3] float32 world-space unit normals (0 for sky)
    labels: np.ndarray  # [H, W] int64 object id (index + 1), 0 for sky


def render(scene: SceneDef, cam: Camera, offsets: Sequence[tuple[float, float]] = SUBPIXEL_OFFSETS) -> Rendering:
    if cam.has_distortion:
        raise ValueError("the ray tracer renders pinhole cameras only")
    h, w = cam.height, cam.width
    o, d = camera_rays(cam)
    t, normal, index = intersect(scene, o, d)  # geometry from the pixel-centre ray only
    rays = [camera_rays(cam, off) for off in (offsets or ((0.0, 0.0),))]
    rgb = shade(scene, np.concatenate([r[0] for r in rays]), np.concatenate([r[1] for r in rays]))[0]
    rgb = rgb.reshape(len(rays), h * w, 3).mean(axis=0)
    return Rendering(rgb=rgb.reshape(h, w, 3).astype(np.float32), depth=t.reshape(h, w).astype(np.float32),
                     normal=normal.reshape(h, w, 3).astype(np.float32) * (index >= 0).reshape(h, w, 1),
                     labels=(index + 1).reshape(h, w))
