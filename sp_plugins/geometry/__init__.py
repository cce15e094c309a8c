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

from sp_plugins.geometry.cleanup import largest_component
from sp_plugins.geometry.io import Frame, OrientedPoints, estimate_normals, load_mesh, load_oriented_points, save_mesh
from sp_plugins.geometry.marching_cubes import evaluate_grid, extract_mesh, mesh_from_grid, refine_vertices
from sp_plugins.geometry.sparse_marching_cubes import sparse_extract_mesh
from sp_plugins.geometry.metrics import directed_distances, mesh_metrics, sample_surface

__all__ = [
    "Frame",
    "OrientedPoints",
    "directed_distances",
    "estimate_normals",
    "evaluate_grid",
    "extract_mesh",
    "largest_component",
    "load_mesh",
    "load_oriented_points",
    "mesh_from_grid",
    "mesh_metrics",
    "refine_vertices",
    "sample_surface",
    "save_mesh",
    "sparse_extract_mesh",
]
