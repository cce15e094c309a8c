"""Mesh and oriented point-cloud input / output (trimesh; pymeshlab for normal estimation),
with the checks that turn bad files into clear errors, and the normalised frame fits run in."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union, cast

import numpy as np
import trimesh
from jaxtyping import Float

from sp_plugins.geometry.metrics import sample_surface

log = logging.getLogger(__name__)

PathLike = Union[str, Path]


def _load_any(path: PathLike):
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: is a folder; give a file inside it" if path.is_dir() else f"{path}: no such file")
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds for a corrupt or unknown file
        raise ValueError(f"{path}: cannot be read as a mesh or point cloud ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        clouds = [g for g in loaded.geometry.values() if isinstance(g, trimesh.PointCloud)]
        if geoms:
            loaded = trimesh.util.concatenate(geoms)
        elif clouds:
            loaded = trimesh.PointCloud(np.vstack([np.asarray(c.vertices) for c in clouds]))
        elif not loaded.geometry:
            raise ValueError(f"{path}: the file is empty (no points, no faces); expected a mesh or an oriented point cloud")
        else:
            raise ValueError(f"{path}: the file holds no triangle mesh or point cloud")
    return loaded


def _check_finite(points: np.ndarray, path: PathLike) -> None:
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} vertices have NaN or inf coordinates; clean the file first")


def load_mesh(path: PathLike) -> trimesh.Trimesh:
    """A triangle mesh with at least one face and finite vertices, else a ValueError saying why.
    Degenerate faces (zero area: repeated or collinear corners) are dropped with a warning: they
    hold no surface, and their zero normals would mislead signs and normals."""
    loaded = _load_any(path)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{path}: the file has no faces; a mesh is needed here (a point cloud cannot serve as ground truth)")
    _check_finite(np.asarray(loaded.vertices), path)
    if loaded.area <= 0:
        raise ValueError(f"{path}: every face is degenerate (zero total area: its corners coincide or are collinear); "
                         "expected a mesh with a surface")
    keep = loaded.area_faces > 0
    if not keep.all():
        log.warning("warning: %s: dropped %d degenerate faces (zero area) of %d", path, int((~keep).sum()), len(keep))
        loaded = trimesh.Trimesh(vertices=loaded.vertices, faces=np.asarray(loaded.faces)[keep], process=False)
    return loaded


@dataclass
class MeshTopology:
    """What an SDF fit of a mesh should know about it (computed on a copy with merged vertices)."""

    boundary_edges: int
    """Edges with one face: the mesh is open (not watertight)."""
    nonmanifold_edges: int
    """Edges shared by more than two faces."""
    parts: int
    """Connected pieces."""
    consistent_winding: bool
    """Neighbouring faces agree on their orientation (so their normals agree on outside)."""

    @property
    def closed(self) -> bool:
        return self.boundary_edges == 0 and self.nonmanifold_edges == 0


def mesh_topology(mesh: trimesh.Trimesh) -> MeshTopology:
    merged = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=True)  # merges duplicate vertices
    _, counts = np.unique(merged.edges_sorted, axis=0, return_counts=True)
    return MeshTopology(
        boundary_edges=int((counts == 1).sum()),
        nonmanifold_edges=int((counts > 2).sum()),
        parts=int(merged.body_count),
        consistent_winding=bool(merged.is_winding_consistent),
    )


@dataclass
class OrientedPoints:
    """Surface samples with unit normals, plus where the normals came from."""

    points: Float[np.ndarray, "n 3"]
    normals: Float[np.ndarray, "n 3"]
    source: str
    """``mesh`` (sampled from faces), ``file`` (normals read from the file) or ``estimated``."""
    mesh: Optional[trimesh.Trimesh] = None
    """The input mesh when the input was one (the default ground truth)."""


def _ply_normals(cloud) -> Optional[np.ndarray]:
    raw = cloud.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    names = raw.keys() if isinstance(raw, dict) else (getattr(getattr(raw, "dtype", None), "names", None) or ())
    # binary PLY: a structured array; ASCII PLY: a dict of columns
    if all(k in names for k in ("nx", "ny", "nz")):
        return np.stack([np.asarray(raw[k]).reshape(-1) for k in ("nx", "ny", "nz")], axis=-1).astype(np.float64)
    return None


def estimate_normals(points: Float[np.ndarray, "n 3"], k: int = 10) -> Float[np.ndarray, "n 3"]:
    """PCA normals from ``k`` neighbours (pymeshlab), oriented away from the centroid: right for
    roughly star-shaped objects, wrong in deep concavities."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(points, dtype=np.float64)))
    ms.compute_normal_for_point_clouds(k=k, viewpos=points.mean(axis=0), flipflag=True)
    normals = ms.current_mesh().vertex_normal_matrix()
    outward = np.sign(np.sum(normals * (points - points.mean(axis=0)), axis=1, keepdims=True))
    return normals * np.where(outward == 0, 1.0, outward)


def load_oriented_points(
    path: PathLike, n_points: int = 200_000, seed: int = 0, estimate_missing_normals: bool = False
) -> OrientedPoints:
    """Oriented points from a mesh (``n_points`` area-uniform samples with face normals) or from
    a point cloud with per-point normals (used as they are).

    A point cloud without normals is refused unless ``estimate_missing_normals``, in which case
    they are estimated with :func:`estimate_normals` and a warning says so.
    """
    nrm: Optional[np.ndarray]  # None: a point cloud without normals
    loaded = _load_any(path)
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces) > 0:
        mesh = load_mesh(path)
        pts, nrm = sample_surface(mesh, n_points, seed)
        return OrientedPoints(pts, nrm, "mesh", mesh)
    if isinstance(loaded, (trimesh.Trimesh, trimesh.PointCloud)):  # a mesh without faces is a cloud
        pts = np.asarray(loaded.vertices, dtype=np.float64)
        nrm = _ply_normals(loaded)
    else:
        raise ValueError(f"{path}: not a mesh or point cloud ({type(loaded).__name__})")
    if len(pts) == 0:
        raise ValueError(f"{path}: the file has no points; expected an oriented point cloud (x, y, z, nx, ny, nz) or a mesh")
    _check_finite(pts, path)
    if not np.ptp(pts, axis=0).max() > 0:
        raise ValueError(f"{path}: all {len(pts)} points coincide at {[round(float(v), 6) for v in pts[0]]}: there is no "
                         "shape to fit; expected points spread over a surface")
    source = "file"
    if nrm is None:
        if not estimate_missing_normals:
            raise ValueError(
                f"{path}: the point cloud has no normals (nx, ny, nz); add them, pass a mesh, or "
                "allow estimating them (sp-fit pointcloud --estimate-normals)"
            )
        log.warning("%s: no normals in the file; estimating them from 10 neighbours (pymeshlab), oriented away from the centroid", path)
        nrm, source = estimate_normals(pts), "estimated"
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    bad = ~np.isfinite(nrm).all(axis=1) | ~(length[:, 0] >= 1e-8)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} of {len(nrm)} normals are zero, NaN or inf (the first at point "
                         f"{int(np.argmax(bad))}); expected a direction at every point: fix them or drop those points")
    return OrientedPoints(pts, nrm / length, source, None)


def save_mesh(mesh: trimesh.Trimesh, path: PathLike) -> Path:
    """Write a mesh (format from the suffix, e.g. ``.ply``); creates the parent folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(str(path))
    return path


@dataclass(frozen=True)
class Frame:
    """A similarity ``x -> (x - center) * scale`` that puts an object in a fixed box.

    Fits run in this frame so that hyperparameters (alpha, grid sizes, thresholds) mean the
    same for a bunny 0.15 wide and a cow 10 wide.
    """

    center: tuple[float, float, float]
    scale: float

    @staticmethod
    def fit(points: Float[np.ndarray, "n 3"], diagonal: float = 1.9) -> "Frame":
        """Centre the bounding box at 0 and scale its diagonal to ``diagonal`` (1.9 keeps every
        shape inside [-0.95, 0.95]^3, leaving a margin in the [-1, 1]^3 domain)."""
        lo, hi = points.min(axis=0), points.max(axis=0)
        diag = float(np.linalg.norm(hi - lo))
        if not diag > 0:
            raise ValueError("the points all coincide: nothing to fit")
        center = cast(tuple[float, float, float], tuple(float(v) for v in (lo + hi) / 2))  # points are [n, 3]
        return Frame(center, diagonal / diag)

    def to_frame(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x) - np.asarray(self.center)) * self.scale

    def from_frame(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x) / self.scale + np.asarray(self.center)

    def mesh_to_frame(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        return trimesh.Trimesh(vertices=self.to_frame(mesh.vertices), faces=np.asarray(mesh.faces), process=False)

    def mesh_from_frame(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        return trimesh.Trimesh(vertices=self.from_frame(mesh.vertices), faces=np.asarray(mesh.faces), process=False)
