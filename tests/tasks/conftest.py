import numpy as np
import pytest
import trimesh

from sp_plugins.geometry import OrientedPoints, sample_surface
from sp_plugins.tasks.fields import EncodingConfig



@pytest.fixture
def tiny_grid():
    return EncodingConfig(levels=4, log2_table_size=12, base_resolution=8, max_resolution=64)


@pytest.fixture(scope="session")
def blob_mesh():
    """A small non-convex closed mesh: a sphere squashed along z with a bump."""
    mesh = trimesh.creation.icosphere(3, radius=1.0)
    v = np.asarray(mesh.vertices).copy()
    v[:, 2] *= 0.6
    v[:, 0] += 0.3 * np.exp(-8 * ((v[:, 1]) ** 2 + (v[:, 2] - 0.3) ** 2))
    return trimesh.Trimesh(v, mesh.faces, process=False)


@pytest.fixture(scope="session")
def blob_points(blob_mesh):
    pts, nrm = sample_surface(blob_mesh, 20_000, seed=0)
    return OrientedPoints(pts, nrm, "mesh", blob_mesh)
