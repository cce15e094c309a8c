"""Cameras on a sphere looking at the origin, deterministic from a seed.

Conventions (the same as Blender's ``transforms.json`` and nerfstudio's `Cameras`):

- ``c2w`` is a 4x4 camera-to-world matrix in the **OpenGL** convention: the camera looks down its
  -Z axis, +Y is up in the image, +X is right. World +Z is up.
- SDFStudio's ``meta_data.json`` stores ``camtoworld`` in the **OpenCV** convention (+Z forward,
  +Y down): `opengl_to_opencv` flips the camera's Y and Z axes; nerfstudio's `sdfstudio` dataparser
  flips them back.
- Pixel (row i, column j) has its centre at image coordinates (j + 0.5, i + 0.5) and the principal
  point is the image centre (W/2, H/2), as nerfstudio's Blender dataparser assumes.
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np
from jaxtyping import Float

MAX_ABS_Z = 0.95
"""Directions stay below ~72 degrees from the poles: a look-at with world-up +Z degenerates there."""

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def fibonacci_directions(n: int, rng: np.random.Generator, hemisphere: bool = False) -> Float[np.ndarray, "n 3"]:
    """`n` unit vectors spread evenly on the sphere (a jittered, randomly rotated Fibonacci spiral).

    Even coverage matters for few views; the jitter and rotation make the set depend on the seed.
    With `hemisphere`, all directions have z >= 0 (cameras above the horizon).
    """
    if n <= 0:
        return np.zeros((0, 3))
    z_low = 0.0 if hemisphere else -MAX_ABS_Z
    bins = (np.arange(n) + rng.uniform(0.1, 0.9, n)) / n
    z = MAX_ABS_Z - bins * (MAX_ABS_Z - z_low)
    azimuth = rng.uniform(0.0, 2.0 * math.pi) + GOLDEN_ANGLE * np.arange(n)
    ring = np.sqrt(1.0 - z**2)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=-1)


def random_directions(n: int, rng: np.random.Generator, hemisphere: bool = False) -> Float[np.ndarray, "n 3"]:
    """`n` independent uniform unit vectors with |z| <= MAX_ABS_Z (z >= 0 with `hemisphere`)."""
    z_low = 0.0 if hemisphere else -MAX_ABS_Z
    z = rng.uniform(z_low, MAX_ABS_Z, n)
    azimuth = rng.uniform(0.0, 2.0 * math.pi, n)
    ring = np.sqrt(1.0 - z**2)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=-1)


def balanced_directions(n: int, rng: np.random.Generator, hemisphere: bool = False) -> Float[np.ndarray, "n 3"]:
    """Fibonacci directions in pairs with opposite azimuth (plus one on the equator when `n` is odd).

    Why: nerfstudio's `sdfstudio` dataparser auto-orients the poses so that the mean camera up
    vector becomes +Z. With these pairs the mean up vector of look-at cameras *is* +Z, so that
    rotation is the identity and nerfstudio's coordinates equal the dataset coordinates.
    """
    half = fibonacci_directions(n // 2, rng, hemisphere)
    mirrored = half * np.array([-1.0, -1.0, 1.0])
    pairs = np.stack([half, mirrored], axis=1).reshape(-1, 3)
    if n % 2:
        azimuth = rng.uniform(0.0, 2.0 * math.pi)
        pairs = np.concatenate([pairs, [[math.cos(azimuth), math.sin(azimuth), 0.0]]])
    return pairs


def look_at_origin(positions: Float[np.ndarray, "n 3"]) -> Float[np.ndarray, "n 4 4"]:
    """OpenGL camera-to-world matrices for cameras at `positions` looking at the origin, world-up +Z."""
    positions = np.asarray(positions, dtype=np.float64)
    back = positions / np.linalg.norm(positions, axis=-1, keepdims=True)  # camera +Z points away from the target
    right = np.cross(np.array([0.0, 0.0, 1.0]), back)
    norms = np.linalg.norm(right, axis=-1, keepdims=True)
    if (norms < 1e-6).any():
        raise ValueError("a camera sits on the world Z axis, where a look-at with up +Z is undefined.")
    right = right / norms
    up = np.cross(back, right)
    c2w = np.zeros((len(positions), 4, 4))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, up, back, positions
    c2w[:, 3, 3] = 1.0
    return c2w


def opengl_to_opencv(c2w: Float[np.ndarray, "*batch 4 4"]) -> Float[np.ndarray, "*batch 4 4"]:
    """Flip the camera's Y and Z axes (OpenGL <-> OpenCV); the flip is its own inverse."""
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[..., :3, 1:3] *= -1.0
    return out


def focal_from_fov(width: int, fov_x: float) -> float:
    """Focal length in pixels for a horizontal field of view `fov_x` (radians), as in transforms.json."""
    return 0.5 * width / math.tan(0.5 * fov_x)


def default_fov(radius: float, distance: float, margin: float = 1.15) -> float:
    """Horizontal field of view (radians) that frames a sphere of `radius` at `distance` with a margin."""
    if distance <= radius:
        raise ValueError(f"camera distance {distance} must exceed the scene radius {radius}.")
    return min(2.0 * margin * math.asin(radius / distance), math.radians(120.0))


def intrinsics(width: int, height: int, fov_x: float) -> Float[np.ndarray, "3 3"]:
    """Pinhole intrinsics with square pixels and the principal point at the image centre."""
    focal = focal_from_fov(width, fov_x)
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def pixel_rays(
    c2w: Float[np.ndarray, "4 4"], K: Float[np.ndarray, "3 3"], width: int, height: int, supersample: int = 1
) -> Tuple[Float[np.ndarray, "h w s 3"], Float[np.ndarray, "h w s 3"]]:
    """World-space ray origins and unit directions through a regular ``supersample^2`` grid per pixel.

    With ``supersample == 1`` the single ray goes through the pixel centre (j + 0.5, i + 0.5).
    """
    offsets = (np.arange(supersample) + 0.5) / supersample
    sub_u, sub_v = np.meshgrid(offsets, offsets, indexing="xy")
    cols, rows = np.meshgrid(np.arange(width), np.arange(height), indexing="xy")
    u = cols[..., None] + sub_u.reshape(-1)  # (h, w, s)
    v = rows[..., None] + sub_v.reshape(-1)
    # OpenGL camera: x right, y up, looking down -z.
    x = (u - K[0, 2]) / K[0, 0]
    y = -(v - K[1, 2]) / K[1, 1]
    dirs_cam = np.stack([x, y, -np.ones_like(x)], axis=-1)
    dirs = dirs_cam @ c2w[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = np.broadcast_to(c2w[:3, 3], dirs.shape)
    return origins, dirs
