"""Mesh clean-up through pymeshlab."""

from __future__ import annotations

import numpy as np
import trimesh


def largest_component(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The connected component with the most faces (drops floaters and detached extra sheets).

    An extra sheet that touches the true surface is part of its component and stays; judge
    floaters with the metrics' ``accuracy`` before and after this, not with this alone.
    Empty meshes come back unchanged.
    """
    if len(mesh.faces) == 0:
        return mesh
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(mesh.vertices, dtype=np.float64),
                               face_matrix=np.asarray(mesh.faces, dtype=np.int32)))
    ms.generate_splitting_by_connected_components(delete_source_mesh=True)
    best = max(ms, key=lambda m: m.face_number(), default=None)
    if best is None:
        return mesh
    return trimesh.Trimesh(vertices=best.vertex_matrix(), faces=best.face_matrix(), process=False)
