"""Mesh sources for synthetic scenes: files, the bundled model, primitives; and normalisation.

A scene's *dataset coordinates* are the mesh's own coordinates after `normalize_mesh`:
``x_dataset = (x_mesh_up - center) * scale``, where ``x_mesh_up`` is the mesh after rotating its
up axis onto +Z. The mesh is centred on its bounding-box centre and fits in a sphere of radius
`radius` (default 0.85), so it sits well inside the [-1, 1]^3 box that both layouts share.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Dict, Tuple, Union

import numpy as np
import trimesh

ASSETS = Path(__file__).resolve().parent / "assets"
"""Bundled meshes. ``spot.ply``: Keenan Crane's Spot (CC0), 5,856 faces, re-saved with +Z up."""

PRIMITIVES: Dict[str, Callable[[], trimesh.Trimesh]] = {
    "sphere": lambda: trimesh.creation.icosphere(subdivisions=3),
    "box": lambda: trimesh.creation.box(extents=(1.0, 0.7, 0.5)),
    "torus": lambda: trimesh.creation.torus(major_radius=0.6, minor_radius=0.25, major_sections=48, minor_sections=24),
    "capsule": lambda: trimesh.creation.capsule(height=0.8, radius=0.35),
}
"""Named primitives, so tests need no mesh files."""

BUNDLED = {"spot": ASSETS / "spot.ply"}

MeshSource = Union[trimesh.Trimesh, str, Path]

_UP_ROTATIONS = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),  # +Y -> +Z
    "x": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),  # +X -> +Z
}


def load_mesh(source: MeshSource) -> trimesh.Trimesh:
    """A triangle mesh from a `trimesh.Trimesh`, a file path, a bundled name or a primitive name.

    An existing file wins over a name. Raises `ValueError` when the source cannot be read or
    has no faces.
    """
    if isinstance(source, trimesh.Trimesh):
        mesh = source.copy()
    else:
        path = Path(source).expanduser()
        name = str(source).lower()
        if path.is_file():
            try:
                mesh = trimesh.load(path, force="mesh", process=True)
            except Exception as error:  # trimesh raises many kinds for unreadable files
                raise ValueError(f"could not read mesh {path}: {str(error).rstrip('.')}. Give a mesh file trimesh reads (.ply, .obj, .off, .stl, .glb).") from None
        elif name in BUNDLED:
            mesh = trimesh.load(BUNDLED[name], force="mesh", process=True)
        elif name in PRIMITIVES:
            mesh = PRIMITIVES[name]()
        else:
            known = ", ".join(sorted([*BUNDLED, *PRIMITIVES]))
            raise ValueError(f"mesh {str(source)!r} is neither an existing file nor a known name ({known}).")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"mesh {source!r} has no triangle faces (a point cloud or an empty file?): give a triangle mesh.")
    if not np.isfinite(mesh.vertices).all():
        raise ValueError(f"mesh {source!r} has non-finite vertex coordinates.")
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    if not 0.0 < extent < np.inf:
        what = "all its vertices coincide" if extent == 0.0 else "its coordinates overflow"
        raise ValueError(f"mesh {source!r} is degenerate ({what}): give a mesh with a surface.")
    return mesh


def normalize_mesh(
    mesh: trimesh.Trimesh, radius: float = 0.85, up_axis: str = "z"
) -> Tuple[trimesh.Trimesh, np.ndarray, float]:
    """Rotate `up_axis` onto +Z, centre on the bounding-box centre, scale into a sphere of `radius`.

    Returns ``(normalised mesh, center, scale)`` with ``x_dataset = (R_up @ x_mesh - center) * scale``;
    `center` is in the rotated frame.
    """
    if up_axis not in _UP_ROTATIONS:
        raise ValueError(f"up_axis must be one of {sorted(_UP_ROTATIONS)}, got {up_axis!r}.")
    if not 0.0 < radius < 1.0:
        raise ValueError(f"radius must be in (0, 1) so the mesh fits the [-1, 1]^3 box, got {radius}.")
    out = mesh.copy()
    out.apply_transform(up_rotation(up_axis))
    center = out.bounds.mean(axis=0)
    extent = np.linalg.norm(out.vertices - center, axis=1).max()
    if extent <= 0.0:
        raise ValueError("mesh is degenerate: all vertices coincide.")
    scale = float(radius / extent)
    out.apply_translation(-center)
    out.apply_scale(scale)
    return out, center, scale


def up_rotation(up_axis: str) -> np.ndarray:
    """4x4 rotation taking the mesh's `up_axis` ('x', 'y' or 'z') onto +Z."""
    transform = np.eye(4)
    transform[:3, :3] = _UP_ROTATIONS[up_axis]
    return transform
