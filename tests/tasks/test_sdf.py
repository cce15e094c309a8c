import numpy as np
import pytest
import torch
import trimesh

from sp_plugins.tasks.sdf import SDFFitConfig, mape, signed_distance


def test_signed_distance_of_a_sphere_watertight_or_not():
    sphere = trimesh.creation.icosphere(4, radius=1.0)
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, (500, 3))
    exact = np.linalg.norm(pts, axis=1) - 1.0
    np.testing.assert_allclose(signed_distance(sphere, pts), exact, atol=5e-3)
    open_sphere = trimesh.Trimesh(sphere.vertices, sphere.faces[:-4], process=False)  # a small hole
    assert not open_sphere.is_watertight
    far_from_hole = np.linalg.norm(pts - sphere.vertices[sphere.faces[-1, 0]], axis=1) > 0.5
    d = signed_distance(open_sphere, pts)
    assert np.mean(np.sign(d[far_from_hole]) == np.sign(exact[far_from_hole])) > 0.99


def test_mape_is_relative():
    t = torch.tensor([0.0, 1.0])
    assert float(mape(torch.tensor([0.01, 1.0]), t)) == pytest.approx(0.5 * (0.01 / 0.01), rel=1e-5)


def test_a_short_direct_fit_lowers_the_loss(blob_mesh, tiny_grid):
    config = SDFFitConfig(steps=100, batch=1024, pool=6000, hidden=(32,), encoding=tiny_grid, lr=5e-3,
                          mesh_resolution=48, refine=2, metric_points=5000)
    trainer = config.setup(blob_mesh)
    surface, near, uniform = trainer.groups
    assert len(surface[0]) == 3000 and len(near[0]) == 1500 and len(uniform[0]) == 1500
    trainer.fit()
    loss = trainer.history["loss"]
    assert np.mean(loss[-10:]) < 0.5 * np.mean(loss[:10])
    mesh, metrics = trainer.evaluate()
    assert len(mesh.faces) > 0 and metrics["completeness"] < 0.05
