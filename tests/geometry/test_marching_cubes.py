import numpy as np
import pytest
import torch
import trimesh

from sp_plugins.geometry import evaluate_grid, extract_mesh, mesh_metrics

R = 0.5


def sphere_sdf(p):
    return p.norm(dim=-1) - R


def non_metric_sphere(p):
    """Same zero set as the sphere, but sqrt-shaped across it: linear interpolation on a grid
    edge misplaces the crossing by a sizeable fraction of the edge."""
    d = p.norm(dim=-1) - R
    return torch.sign(d) * d.abs().sqrt()


def radial_error(mesh):
    return np.abs(np.linalg.norm(mesh.vertices, axis=1) - R)


def test_sphere_mesh_is_accurate_closed_and_outward():
    mesh = extract_mesh(sphere_sdf, (-1.0, 1.0), 40)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * R**3, rel=0.02)  # > 0: outward normals
    assert radial_error(mesh).mean() < 5e-4  # h = 0.05, so well below 1% of an edge
    gt = trimesh.creation.icosphere(6, radius=R)
    m = mesh_metrics(mesh, gt, n_points=100_000)
    # 100k samples put two samplings of this sphere ~1.5e-3 (of the diagonal) apart: the
    # bound allows that floor plus a little.
    assert m["chamfer"] < 2.2e-3
    assert m["normal_consistency"] > 0.99
    assert m["fscore"] == 1.0


def test_bisection_fixes_a_non_metric_field():
    plain = extract_mesh(non_metric_sphere, (-1.0, 1.0), 24)
    refined = extract_mesh(non_metric_sphere, (-1.0, 1.0), 24, refine=8)
    assert len(plain.faces) == len(refined.faces)  # same topology, vertices moved
    e_plain, e_refined = radial_error(plain).mean(), radial_error(refined).mean()
    assert e_plain > 2e-3  # the stair-step error is real ...
    assert e_refined < 0.02 * e_plain  # ... and bisection removes it
    gt = trimesh.creation.icosphere(6, radius=R)
    c_plain = mesh_metrics(plain, gt, n_points=50_000)["chamfer"]
    c_refined = mesh_metrics(refined, gt, n_points=50_000)["chamfer"]
    assert c_refined < c_plain


def test_refinement_moves_vertices_along_their_edge_onto_the_surface():
    a = extract_mesh(sphere_sdf, (-1.0, 1.0), 24)
    b = extract_mesh(sphere_sdf, (-1.0, 1.0), 24, refine=10)
    move = np.abs(np.asarray(a.vertices) - np.asarray(b.vertices))
    assert ((move > 0).sum(axis=1) <= 1).all()  # one axis: the vertex's grid edge
    assert move.max() < 2 / 23  # never leaves that edge
    # even an exact SDF is curved along an edge that grazes the sphere: linear interpolation
    # errs there, bisection does not
    assert radial_error(a).max() > 1e-3
    assert radial_error(b).max() < 1e-5


def test_chunking_does_not_change_the_grid():
    big = evaluate_grid(sphere_sdf, (-1.0, 1.0), (9, 10, 11), chunk=1 << 16)
    small = evaluate_grid(sphere_sdf, (-1.0, 1.0), (9, 10, 11), chunk=7)
    assert big.shape == (9, 10, 11)
    np.testing.assert_array_equal(big, small)
    # volume[i, j, k] = f(x_i, y_j, z_k), corners at the bounds
    assert big[0, 0, 0] == pytest.approx(np.sqrt(3) - R, abs=1e-6)
    assert big[4, 0, 0] == pytest.approx(np.sqrt(2) - R, abs=1e-6)  # x_4 = 0


def test_anisotropic_bounds_and_level():
    lo, hi = np.array([-1.0, -0.8, -0.6]), np.array([1.0, 0.8, 0.6])
    mesh = extract_mesh(sphere_sdf, (lo, hi), 48, level=0.05, refine=4)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - (R + 0.05)).mean() < 1e-4


def test_no_crossing_gives_an_empty_mesh_and_nan_is_refused():
    empty = extract_mesh(lambda p: p.norm(dim=-1) + 1.0, (-1.0, 1.0), 8)
    assert len(empty.faces) == 0
    with pytest.raises(ValueError, match="NaN"):
        extract_mesh(lambda p: torch.full(p.shape[:1], float("nan")), (-1.0, 1.0), 8)
    with pytest.raises(ValueError, match="values for"):
        extract_mesh(lambda p: p, (-1.0, 1.0), 8)
    with pytest.raises(ValueError, match="lo < hi"):
        extract_mesh(sphere_sdf, (1.0, -1.0), 8)
