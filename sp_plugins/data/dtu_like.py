"""DTU-like surroundings for a synthetic scene: a textured ground, a textured backdrop, a frontal cap of cameras.

What makes DTU hard for a hash-grid NeuS, and what a scene on white with cameras on a full sphere
lacks: every pixel is opaque (a table under the object, a backdrop behind it, no masks), the
cameras cover a frontal cap only (49-64 views, none from behind or below), and the colour outside
the object's sphere must be explained by a background model. Here:

- the object (normalised into a sphere of ``radius`` at the origin) stands on a ground plane at
  its lowest point, textured with a checker board and stripes;
- everything sits inside a backdrop sphere of radius `BACKDROP_RADIUS`, textured with larger
  blobs, so every camera ray hits something;
- the object casts a shadow on the ground (shadow rays against the object only);
- cameras lie on a cap in front of the object: a jittered grid of ``rows x cols`` directions,
  azimuth within ``+-azimuth_span/2`` of the -Y axis and elevation in ``elevation``.

Colours depend only on position and normal (a fixed distant light), so the views are
consistent, as a radiance field assumes. The object mask of a view (the fraction of each pixel's
sub-rays whose first hit is the object) is what metrics use; training sees no mask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
import trimesh
from jaxtyping import Float

from sp_plugins.data.render import (
    AMBIENT,
    LIGHT_DIRECTION,
    albedo,
    interpolated_normals,
    lambert_facing_viewer,
    per_pixel,
    ray_intersector,
    view_rays,
)

BACKDROP_RADIUS = 8.0
"""Radius of the textured sphere around everything (dataset units; the object fits radius 0.85)."""
GROUND_HALF_SIZE = 0.7 * BACKDROP_RADIUS
"""Half the side of the square ground plane (it stays inside the backdrop sphere)."""

OBJECT, GROUND, BACKDROP = 0, 1, 2


@dataclass(frozen=True)
class CapCameras:
    """Where a DTU-like set of cameras may sit: directions from the origin, in degrees."""

    azimuth_span: float = 100.0
    """Total azimuth range, centred on the -Y axis (the object's front)."""
    elevation: Tuple[float, float] = (12.0, 55.0)
    """Elevation range above the horizon."""

    def __post_init__(self) -> None:
        low, high = self.elevation
        if not 0.0 < self.azimuth_span <= 360.0:
            raise ValueError(f"azimuth_span must be in (0, 360] degrees, got {self.azimuth_span}.")
        if not -80.0 <= low < high <= 80.0:
            raise ValueError(f"elevation must be an increasing pair within [-80, 80] degrees, got {self.elevation}.")

    def grid(self, n: int, rng: np.random.Generator) -> Float[np.ndarray, "n 3"]:
        """`n` unit directions on a jittered grid over the cap (rows of equal elevation, as DTU's arcs)."""
        if n <= 0:
            return np.zeros((0, 3))
        rows = max(1, int(round(math.sqrt(n * (self.elevation[1] - self.elevation[0]) / self.azimuth_span))))
        rows = min(rows, n)
        cols = int(math.ceil(n / rows))
        cells = [(r, c) for r in range(rows) for c in range(cols)][:n]
        r = np.array([cell[0] for cell in cells], dtype=np.float64)
        c = np.array([cell[1] for cell in cells], dtype=np.float64)
        u = (c + rng.uniform(0.3, 0.7, n)) / cols
        v = (r + rng.uniform(0.3, 0.7, n)) / rows
        return self._directions(u, v)

    def random(self, n: int, rng: np.random.Generator) -> Float[np.ndarray, "n 3"]:
        """`n` independent directions, uniform in azimuth and elevation over the cap (held-out views)."""
        return self._directions(rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 1.0, n))

    def _directions(self, u: np.ndarray, v: np.ndarray) -> Float[np.ndarray, "n 3"]:
        azimuth = np.radians(-90.0 + (u - 0.5) * self.azimuth_span)  # -90 degrees: the -Y axis
        elevation = np.radians(self.elevation[0] + v * (self.elevation[1] - self.elevation[0]))
        ring = np.cos(elevation)
        return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), np.sin(elevation)], axis=-1)


def surroundings(object_mesh: trimesh.Trimesh) -> Tuple[trimesh.Trimesh, float]:
    """The ground plane (at the object's lowest point) and the backdrop sphere, as one mesh.

    Returns ``(mesh, ground_z)``; the mesh's first 2 faces are the ground, the rest the backdrop.
    """
    ground_z = float(object_mesh.bounds[0, 2])
    h = GROUND_HALF_SIZE
    ground = trimesh.Trimesh(
        vertices=[[-h, -h, ground_z], [h, -h, ground_z], [h, h, ground_z], [-h, h, ground_z]],
        faces=[[0, 1, 2], [0, 2, 3]],
        process=False,
    )
    backdrop = trimesh.creation.icosphere(subdivisions=3, radius=BACKDROP_RADIUS)
    return trimesh.util.concatenate([ground, backdrop]), ground_z


def ground_albedo(points: Float[np.ndarray, "n 3"]) -> Float[np.ndarray, "n 3"]:
    """A checker board (0.25 units) modulated by diagonal stripes: texture a hash grid must fit."""
    checker = (np.floor(points[:, 0] / 0.25) + np.floor(points[:, 1] / 0.25)) % 2
    stripes = 0.5 + 0.5 * np.sin(7.0 * (points[:, 0] + 0.6 * points[:, 1]))
    base = np.array([0.62, 0.5, 0.38]) + 0.25 * checker[:, None] * np.array([1.0, 0.9, 0.7])
    return np.clip(base * (0.75 + 0.25 * stripes[:, None]), 0.0, 1.0)


def backdrop_albedo(points: Float[np.ndarray, "n 3"]) -> Float[np.ndarray, "n 3"]:
    """Soft coloured blobs over the backdrop sphere (periods of about 2-4 units)."""
    p = points / BACKDROP_RADIUS
    waves = np.sin(np.stack([5.1 * p[:, 0] + 2.3 * p[:, 2], 4.3 * p[:, 1] - 3.1 * p[:, 2], 6.7 * p[:, 2] + 1.7 * p[:, 0]], -1))
    return np.clip(np.array([0.45, 0.5, 0.55]) + 0.2 * waves, 0.0, 1.0)


def render_dtu_views(
    object_mesh: trimesh.Trimesh,
    c2w: Float[np.ndarray, "n 4 4"],
    K: Float[np.ndarray, "3 3"],
    width: int,
    height: int,
    *,
    supersample: int = 1,
    backend: str = "auto",
    progress: bool = False,
    desc: str = "rendering",
) -> Tuple[Float[np.ndarray, "n h w 3"], Float[np.ndarray, "n h w"]]:
    """Opaque RGB images of the object in its surroundings, and each pixel's object coverage in [0, 1]."""
    env, _ = surroundings(object_mesh)
    scene = trimesh.util.concatenate([object_mesh, env])
    n_object = len(object_mesh.faces)
    part = np.full(len(scene.faces), BACKDROP)
    part[:n_object] = OBJECT
    part[n_object : n_object + 2] = GROUND
    caster = ray_intersector(scene, backend)
    occluder = ray_intersector(object_mesh, backend)  # shadows: only the object blocks the light
    images = np.zeros((len(c2w), height, width, 3), dtype=np.float32)
    masks = np.zeros((len(c2w), height, width), dtype=np.float32)
    for index, origins, dirs in view_rays(c2w, K, width, height, supersample, progress, desc):
        points, ray_ids, triangles = caster.intersects_location(origins, dirs, multiple_hits=False)
        if len(ray_ids) != len(dirs):
            raise RuntimeError(f"{len(dirs) - len(ray_ids)} camera rays escaped the backdrop sphere: a camera outside it?")
        view = dirs[ray_ids]
        kind = part[triangles]
        normals = np.zeros_like(points)
        on_object = kind == OBJECT
        if on_object.any():
            normals[on_object] = interpolated_normals(object_mesh, points[on_object], triangles[on_object])
        normals[kind == GROUND] = (0.0, 0.0, 1.0)
        normals[kind == BACKDROP] = -points[kind == BACKDROP]
        lambert, normals = lambert_facing_viewer(normals, view)
        lit = kind != BACKDROP
        if lit.any():  # shadow rays from object and ground points towards the light
            starts = points[lit] + 1e-3 * normals[lit]
            blocked = occluder.intersects_any(starts, np.broadcast_to(LIGHT_DIRECTION, starts.shape))
            shadowed = np.zeros(len(points), dtype=bool)
            shadowed[np.flatnonzero(lit)[blocked]] = True
            lambert = np.where(shadowed, 0.0, lambert)
        colour = np.empty_like(points)
        colour[on_object] = albedo(points[on_object])
        colour[kind == GROUND] = ground_albedo(points[kind == GROUND])
        colour[kind == BACKDROP] = backdrop_albedo(points[kind == BACKDROP])
        light = np.where(kind == BACKDROP, 1.0, AMBIENT + (1.0 - AMBIENT) * lambert)
        shaded = np.zeros((len(dirs), 3))
        shaded[ray_ids] = np.clip(colour * light[:, None], 0.0, 1.0)
        hit_object = np.zeros(len(dirs))
        hit_object[ray_ids] = on_object
        images[index] = per_pixel(shaded, height, width).mean(axis=2)
        masks[index] = per_pixel(hit_object, height, width).mean(axis=2)
    return images, masks


def dtu_like_fov(radius: float, distance: float, width: int, height: int) -> float:
    """Horizontal field of view (radians) in which the object's sphere spans about 80% of the image height,
    leaving ground and backdrop around it as in DTU's frames."""
    if distance <= radius:
        raise ValueError(f"camera distance {distance} must exceed the scene radius {radius}.")
    half_vertical = math.asin(radius / distance) / 0.8
    return 2.0 * math.atan(math.tan(half_vertical) * width / height)


def default_dtu_resolution(resolution: Optional[object]) -> object:
    """DTU's 4:3 frames at CPU size when no resolution is given."""
    return (96, 72) if resolution is None else resolution
