"""Surface metrics between a reconstruction and a ground truth, on uniformly sampled points.

Both meshes are sampled uniformly by area (trimesh) and matched by nearest neighbour (scipy's
cKDTree). Distances are divided by ``unit``; :func:`mesh_metrics` defaults it to the ground
truth's bounding-box diagonal, so the numbers do not depend on the mesh's scale. With
``n`` samples per mesh, two samplings of the same surface are about ``0.5 * sqrt(area / n)``
apart: that floor is part of every value here (about 1e-3 of the diagonal at 200k points on a
compact shape), so compare metrics computed with the same ``n_points``.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import trimesh
from jaxtyping import Float
from scipy.spatial import cKDTree


def sample_surface(
    mesh: trimesh.Trimesh, n: int, seed: int = 0
) -> tuple[Float[np.ndarray, "n 3"], Float[np.ndarray, "n 3"]]:
    """``n`` points uniform by area with their face normals (unit length)."""
    if len(mesh.faces) == 0:
        raise ValueError("sample_surface: the mesh has no faces")
    points, face_index = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[face_index], dtype=np.float64)


def directed_distances(
    src: Float[np.ndarray, "n 3"], dst: Float[np.ndarray, "m 3"], dst_tree: Optional[cKDTree] = None
) -> tuple[Float[np.ndarray, " n"], np.ndarray]:
    """Distance from every ``src`` point to its nearest ``dst`` point, and that point's index.

    The tree is built with sliding-midpoint splits and uncompacted nodes: with scipy's defaults,
    queries far from a reconstruction that missed the surface (a blob, a fog mesh: mean distance a
    quarter of the diagonal) took 4.5 s for 50k points where these take 0.5 s, and matched points
    cost the same (0.36 vs 0.34 s for 200k); the distances are exact either way."""
    tree = dst_tree if dst_tree is not None else cKDTree(dst, balanced_tree=False, compact_nodes=False)
    dist, idx = tree.query(src, k=1, workers=1)
    return dist, idx


def mesh_metrics(
    pred: trimesh.Trimesh,
    gt: trimesh.Trimesh,
    *,
    n_points: int = 200_000,
    fscore_threshold: float = 0.01,
    seed: int = 0,
    unit: Optional[float] = None,
) -> dict:
    """Chamfer distance, normal consistency and F-score of ``pred`` against ``gt``.

    Args:
        n_points: samples per mesh.
        fscore_threshold: a point counts as matched when its nearest neighbour on the other
            surface is closer than this (in units of ``unit``: 0.01 = 1% of the diagonal by default).
        seed: sampling seed (the same seed on the same mesh gives the same points).
        unit: distances are divided by it; None = ``gt``'s bounding-box diagonal.

    Returns:
        dict with
        ``chamfer`` = (accuracy + completeness) / 2, the symmetric mean nearest-neighbour L2
        distance; ``accuracy`` = mean distance pred -> gt (floaters and extra sheets raise it);
        ``completeness`` = mean distance gt -> pred (missing or misplaced true surface raises it);
        ``normal_consistency`` = mean ``|cos|`` between matched normals, averaged over both
        directions (1 is perfect); ``precision``, ``recall``, ``fscore`` at the threshold;
        ``unit``, ``n_points``, ``area_ratio`` (pred area / gt area: about 2 means a second
        sheet). An empty ``pred`` gives infinite distances and zero scores.
    """
    if len(gt.faces) == 0:
        raise ValueError("mesh_metrics: the ground-truth mesh has no faces")
    if n_points < 1:
        raise ValueError(f"n_points={n_points}: must be >= 1")
    if unit is None:
        unit = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    if not (np.isfinite(unit) and unit > 0):
        raise ValueError(f"unit={unit!r}: must be a finite number > 0")
    base = dict(unit=unit, n_points=int(n_points), fscore_threshold=float(fscore_threshold))
    if len(pred.faces) == 0 or pred.area <= 0:
        return dict(
            base, chamfer=float("inf"), accuracy=float("inf"), completeness=float("inf"),
            normal_consistency=0.0, precision=0.0, recall=0.0, fscore=0.0, area_ratio=0.0,
        )
    p_pts, p_nrm = sample_surface(pred, n_points, seed)
    g_pts, g_nrm = sample_surface(gt, n_points, seed + 1)
    d_pg, i_pg = directed_distances(p_pts, g_pts)
    d_gp, i_gp = directed_distances(g_pts, p_pts)
    d_pg, d_gp = d_pg / unit, d_gp / unit
    accuracy, completeness = float(d_pg.mean()), float(d_gp.mean())
    nc_p = np.abs(np.sum(p_nrm * g_nrm[i_pg], axis=1)).mean()
    nc_g = np.abs(np.sum(g_nrm * p_nrm[i_gp], axis=1)).mean()
    precision = float((d_pg < fscore_threshold).mean())
    recall = float((d_gp < fscore_threshold).mean())
    fscore = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return dict(
        base,
        chamfer=0.5 * (accuracy + completeness),
        accuracy=accuracy,
        completeness=completeness,
        normal_consistency=float(0.5 * (nc_p + nc_g)),
        precision=precision,
        recall=recall,
        fscore=float(fscore),
        area_ratio=float(pred.area / gt.area),
    )
