"""Meshing and surface metrics for fitted fields.

    from sp_plugins.geometry import extract_mesh, mesh_metrics, largest_component

- :func:`extract_mesh`: marching cubes (scikit-image) of ``sdf_fn`` on a chunked grid, with
  optional bisection refinement of the vertices.
- :func:`sparse_extract_mesh`: the same at high resolution, coarse to fine and only near the
  surface (brick-wise scikit-image marching cubes), for fields that are expensive to query.
- :func:`mesh_metrics`: Chamfer (with accuracy / completeness split), normal consistency,
  F-score on area-uniform samples (scipy cKDTree), relative to the ground truth's diagonal.
- :func:`largest_component`: pymeshlab clean-up.
- I/O: :func:`load_mesh`, :func:`load_oriented_points`, :func:`save_mesh`, :class:`Frame`.
"""

from sp_plugins._lazy import lazy_attribute

_WHERE = {
    "largest_component": "cleanup",
    **dict.fromkeys(["Frame", "OrientedPoints", "estimate_normals", "load_mesh", "load_oriented_points", "save_mesh"], "io"),
    **dict.fromkeys(["evaluate_grid", "extract_mesh", "mesh_from_grid", "refine_vertices"], "marching_cubes"),
    "sparse_extract_mesh": "sparse_marching_cubes",
    **dict.fromkeys(["directed_distances", "mesh_metrics", "sample_surface"], "metrics"),
}
"""Where each public name lives: loaded on first use (PEP 562), so that mesh I/O and metrics (a
sweep's soundness check, in every trial's Ray worker) do not import torch with marching cubes."""


def __getattr__(name: str):
    return lazy_attribute(__name__, _WHERE, name)


def __dir__():
    return sorted(set(globals()) | set(__all__))


__all__ = sorted(_WHERE)
