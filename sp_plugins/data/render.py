"""Render a mesh with a library ray caster: procedural albedo, Lambertian + ambient shading.

Everything that colours a surface point depends on its position and normal only (a fixed world
light, an albedo that is a smooth function of position), so the images are view-consistent, as a
radiance field assumes. Rays are cast by trimesh: its Embree backend (``embreex``) when it imports,
otherwise its rtree-based triangle intersector.
"""

from __future__ import annotations

import warnings
from typing import Iterator, Optional, Tuple

import numpy as np
import trimesh
from jaxtyping import Float
from tqdm.auto import tqdm

from sp_plugins.data.cameras import pixel_rays

LIGHT_DIRECTION = np.array([0.4, -0.3, 0.85]) / np.linalg.norm([0.4, -0.3, 0.85])
"""Direction towards a fixed distant light, in dataset coordinates."""
AMBIENT = 0.4

_ALBEDO_MIX = 2.2 * np.array([[2.1, -1.3, 0.7], [0.9, 1.8, -1.5], [-1.2, 0.6, 2.3]])  # about 1-2 periods across the object
_ALBEDO_PHASE = np.array([0.5, 2.6, 4.7])


def ray_intersector(mesh: trimesh.Trimesh, backend: str = "auto"):
    """trimesh's ray intersector for `mesh`: 'embree' (embreex), 'triangle' (rtree) or 'auto'."""
    if backend not in ("auto", "embree", "triangle"):
        raise ValueError(f"backend must be 'auto', 'embree' or 'triangle', got {backend!r}.")
    if backend in ("auto", "embree"):
        try:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            return RayMeshIntersector(mesh)
        except Exception:  # embreex missing or broken on this platform
            if backend == "embree":
                raise ValueError("the Embree ray caster is unavailable: `pip install embreex`, or use backend='triangle'.") from None
            warnings.warn("embreex is not installed: falling back to trimesh's rtree ray caster, about 100x slower.", stacklevel=2)
    from trimesh.ray.ray_triangle import RayMeshIntersector

    return RayMeshIntersector(mesh)


def albedo(points: Float[np.ndarray, "n 3"]) -> Float[np.ndarray, "n 3"]:
    """A smooth colour field over dataset coordinates, in [0.2, 0.9]."""
    return 0.55 + 0.35 * np.sin(points @ _ALBEDO_MIX.T + _ALBEDO_PHASE)


def interpolated_normals(mesh: trimesh.Trimesh, points: Float[np.ndarray, "n 3"], triangles: np.ndarray) -> Float[np.ndarray, "n 3"]:
    """Vertex normals of `mesh` interpolated at hit `points` on `triangles` (not normalised)."""
    barycentric = trimesh.triangles.points_to_barycentric(mesh.triangles[triangles], points)
    return np.einsum("nk,nkd->nd", barycentric, mesh.vertex_normals[mesh.faces[triangles]])


def lambert_facing_viewer(normals: Float[np.ndarray, "n 3"], view_dirs: Float[np.ndarray, "n 3"]):
    """``(lambert, unit normals)``: normals flipped to face the viewer, and their cosine with the light."""
    normals = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    normals = normals * np.where(np.einsum("nd,nd->n", normals, view_dirs) > 0.0, -1.0, 1.0)[:, None]
    return np.clip(normals @ LIGHT_DIRECTION, 0.0, 1.0), normals


def shade(
    mesh: trimesh.Trimesh,
    points: Float[np.ndarray, "n 3"],
    triangles: np.ndarray,
    view_dirs: Float[np.ndarray, "n 3"],
) -> Float[np.ndarray, "n 3"]:
    """Albedo times (ambient + Lambert) at hit `points` on `triangles`, with interpolated vertex normals.

    Normals are flipped to face the viewer, so open meshes and inverted windings shade sensibly.
    """
    lambert, _ = lambert_facing_viewer(interpolated_normals(mesh, points, triangles), view_dirs)
    return np.clip(albedo(points) * (AMBIENT + (1.0 - AMBIENT) * lambert[:, None]), 0.0, 1.0)


def view_rays(
    c2w: Float[np.ndarray, "n 4 4"],
    K: Float[np.ndarray, "3 3"],
    width: int,
    height: int,
    supersample: int = 1,
    progress: bool = False,
    desc: str = "rendering",
) -> Iterator[Tuple[int, Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]]:
    """``(index, origins, dirs)`` of each view, ``m = height * width * supersample**2`` rays with a
    pixel's sub-rays adjacent (:func:`per_pixel` groups them again); a progress bar when asked."""
    for index in tqdm(range(len(c2w)), desc=desc, unit="view", disable=not progress):
        origins, dirs = pixel_rays(c2w[index], K, width, height, supersample)
        yield index, origins.reshape(-1, 3), dirs.reshape(-1, 3)


def per_pixel(values: Float[np.ndarray, " m *c"], height: int, width: int) -> Float[np.ndarray, "h w s *c"]:
    """Per-ray values of :func:`view_rays` grouped by pixel: axis 2 holds a pixel's ``s`` sub-rays."""
    return values.reshape(height, width, -1, *values.shape[1:])


def render_views(
    mesh: trimesh.Trimesh,
    c2w: Float[np.ndarray, "n 4 4"],
    K: Float[np.ndarray, "3 3"],
    width: int,
    height: int,
    supersample: int = 1,
    backend: str = "auto",
    progress: bool = False,
    intersector: Optional[object] = None,
    desc: str = "rendering",
) -> Float[np.ndarray, "n h w 4"]:
    """Straight-alpha RGBA images of `mesh` seen by OpenGL cameras `c2w` with intrinsics `K`.

    ``supersample`` s casts s*s rays per pixel (a regular grid) and averages them: alpha is the
    covered fraction, RGB the mean colour of the covered sub-rays.
    """
    caster = intersector if intersector is not None else ray_intersector(mesh, backend)
    images = np.zeros((len(c2w), height, width, 4), dtype=np.float32)
    for index, origins, dirs in view_rays(c2w, K, width, height, supersample, progress, desc):
        locations, ray_ids, triangles = caster.intersects_location(origins, dirs, multiple_hits=False)
        colour = np.zeros((len(dirs), 3))
        hit = np.zeros(len(dirs))
        if len(ray_ids):
            colour[ray_ids] = shade(mesh, locations, triangles, dirs[ray_ids])
            hit[ray_ids] = 1.0
        colour = per_pixel(colour, height, width).sum(axis=2)
        hit = per_pixel(hit, height, width).sum(axis=2)
        images[index, ..., :3] = colour / np.maximum(hit, 1.0)[..., None]
        images[index, ..., 3] = hit / supersample**2
    return images
