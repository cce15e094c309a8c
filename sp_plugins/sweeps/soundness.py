"""Is a fitted SDF *sound*: one sheet where the surface is, negative inside, positive outside?

A hash grid fitted without geometric initialisation often grows a second zero level (a shell)
or ends up of one sign nearly everywhere, while its Chamfer distance can still look fine; the
robustness study counts sound fields instead. The test (as in ``bench/pointcloud_sdf.py``): the
reconstructed / true surface area within (0.75, 1.3) and the negative share of the domain
within a factor 1.5 of the true interior's share.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

AREA_RANGE = (0.75, 1.3)
NEGATIVE_FACTOR = 1.5


def true_negative_fraction(mesh_path: Path, frame_diagonal: float = 1.9, resolution: int = 48) -> float:
    """Share of the ``[-1, 1]^3`` domain inside the true mesh, in the fitting frame (bounding box
    centred, diagonal ``frame_diagonal``): ray containment for a watertight mesh, else the side of
    the nearest oriented surface sample (meshes with holes)."""
    from scipy.spatial import cKDTree

    from sp_plugins.geometry import Frame, load_mesh, sample_surface  # defers trimesh (a Ray worker imports this)

    mesh = load_mesh(mesh_path)
    frame = Frame.fit(np.asarray(mesh.vertices), frame_diagonal)
    mesh = frame.mesh_to_frame(mesh)
    axis = np.linspace(-1.0, 1.0, resolution)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    if mesh.is_watertight:
        return float(mesh.contains(grid).mean())
    points, normals = sample_surface(mesh, 200_000, seed=0)
    _, idx = cKDTree(points).query(grid, workers=1)
    return float((np.sum((grid - points[idx]) * normals[idx], axis=1) < 0).mean())


def is_sound(area_ratio: float, negative_fraction: float, true_negative: float) -> bool:
    """One sheet and the right sign: see the module docstring."""
    if not (true_negative > 0 and np.isfinite(area_ratio) and np.isfinite(negative_fraction)):
        return False
    ratio = negative_fraction / true_negative
    return bool(AREA_RANGE[0] < area_ratio < AREA_RANGE[1] and 1 / NEGATIVE_FACTOR < ratio < NEGATIVE_FACTOR)
