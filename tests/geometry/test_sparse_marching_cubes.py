"""Coarse-to-fine marching cubes: the same mesh as the dense grid, from a fraction of the queries."""

import numpy as np
import pytest
import torch

from sp_plugins.geometry import evaluate_grid, extract_mesh, sparse_extract_mesh
from sp_plugins.geometry.sparse_marching_cubes import coarse_levels

R = 0.4987  # not a multiple of the cell size: no field value is exactly 0 on the grid


def sphere(points):
    return points.norm(dim=-1) - R


class Counted:
    def __init__(self, fn):
        self.fn, self.points = fn, 0

    def __call__(self, points):
        self.points += len(points)
        return self.fn(points)


def _sorted_rows(a):
    return a[np.lexsort(a.T[::-1])]


def test_same_mesh_as_the_dense_grid_from_a_fraction_of_the_points():
    counted = Counted(sphere)
    sparse = sparse_extract_mesh(counted, (-1.0, 1.0), 128, progress=False)
    dense = extract_mesh(sphere, (-1.0, 1.0), 129)
    assert len(sparse.vertices) == len(dense.vertices) and len(sparse.faces) == len(dense.faces)
    np.testing.assert_allclose(_sorted_rows(np.asarray(sparse.vertices)), _sorted_rows(np.asarray(dense.vertices)), atol=1e-6)
    assert counted.points < 0.2 * 129**3
    assert sparse.is_watertight and sparse.volume == pytest.approx(4 / 3 * np.pi * R**3, rel=1e-3)  # outward


def test_bricks_weld_into_one_closed_surface_at_high_resolution():
    counted = Counted(sphere)
    mesh = sparse_extract_mesh(counted, (-1.0, 1.0), 192, brick=16, progress=False)
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 1
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - R).max() < 2 / 192 * 0.1
    assert counted.points < 0.1 * 193**3  # the band around the sphere


def test_any_resolution_and_a_box_that_is_not_a_cube():
    lo, hi = np.array([-1.0, -0.7, -0.6]), np.array([1.0, 0.7, 0.6])
    mesh = sparse_extract_mesh(sphere, (lo, hi), 100, progress=False)
    assert mesh.is_watertight
    assert (mesh.vertices >= lo - 1e-9).all() and (mesh.vertices <= hi + 1e-9).all()
    # a surface cut by the box: open where it leaves, nothing outside
    cut = sparse_extract_mesh(lambda p: p.norm(dim=-1) - 0.8, (lo, hi), 100, progress=False)
    assert len(cut.faces) > 0 and not cut.is_watertight
    assert (cut.vertices >= lo - 1e-9).all() and (cut.vertices <= hi + 1e-9).all()


def test_small_parts_inside_one_coarse_cell_are_found():
    centres = torch.tensor([[0.3, 0.3, 0.3], [-0.45, 0.1, -0.2]])

    def two_balls(p):  # one ball smaller than a coarse cell (2/16 wide here)
        d = (p[:, None, :] - centres[None]).norm(dim=-1) - torch.tensor([0.3, 0.04])
        return d.min(dim=1).values

    mesh = sparse_extract_mesh(two_balls, (-1.0, 1.0), 256, coarse=16, progress=False)
    parts = mesh.split(only_watertight=True)
    assert len(parts) == 2
    small = min(parts, key=lambda m: m.volume)
    assert small.volume == pytest.approx(4 / 3 * np.pi * 0.04**3, rel=0.05)


def test_unevaluated_points_keep_their_sign():
    from sp_plugins.geometry import sparse_marching_cubes as smc

    # the finest grid each brick meshes: exact near the surface, the right sign elsewhere
    grids = []
    original = smc._brick_volume
    smc._brick_volume = lambda *a: grids.append((a[1].copy(), original(*a))) or grids[-1][1]
    try:
        sparse_extract_mesh(sphere, (-1.0, 1.0), 64, brick=64, progress=False)
    finally:
        smc._brick_volume = original
    (_, grid), = grids
    dense = evaluate_grid(sphere, (-1.0, 1.0), 65).astype(np.float32)
    assert np.all(np.sign(grid) == np.sign(dense))
    near = np.abs(dense) < 2 / 64
    np.testing.assert_allclose(grid[near], dense[near], atol=1e-6)


def test_empty_and_broken_fields():
    assert len(sparse_extract_mesh(lambda p: p.norm(dim=-1) + 1.0, (-1.0, 1.0), 64, progress=False).faces) == 0
    with pytest.raises(ValueError, match="NaN"):
        sparse_extract_mesh(lambda p: torch.full((len(p),), float("nan")), (-1.0, 1.0), 64, progress=False)
    with pytest.raises(ValueError, match="resolution"):
        sparse_extract_mesh(sphere, (-1.0, 1.0), 1, progress=False)
    assert coarse_levels(512, 32) == (4, 32) and coarse_levels(100, 32) == (1, 50) and coarse_levels(20, 32) == (0, 20)
