"""Exact values of the point cloud -> SDF task (issue 44): in one training step the field is
queried at the paper's ``x + alpha * eps`` (K draws averaged), folded into the frame's box
``[-1, 1]^3``, and the SIREN terms get the SDF there and its gradient with respect to ``x``
(the perturbed field's: the fold's sign included), computed here from the raw seeded draws.
Each test names the mutation of ``sp_plugins/tasks/pointcloud.py`` / ``common.py`` it kills."""

from __future__ import annotations

import copy

import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.tasks import pointcloud
from sp_plugins.tasks.pointcloud import PointCloudSDFConfig
from tests.helpers.exact import Recorder, folded_query

SP_SEED = 5


def batch_of(trainer, config) -> torch.Tensor:
    """The step's plain batch, drawn as the task does from the batch generator seeded ``config.seed``:
    surface points, then uniform points in the box."""
    g = torch.Generator().manual_seed(config.seed)
    idx = torch.randint(len(trainer.points), (config.surface_batch,), generator=g)
    xo = torch.rand(config.space_batch, 3, generator=g) * 2.0 - 1.0
    return torch.cat([trainer.points[idx], xo]), idx


@pytest.mark.parametrize("k", [1, 3])
def test_one_step_queries_x_plus_alpha_eps_in_the_frame_box_and_takes_the_gradient_of_the_mean(k, blob_points, tiny_grid, monkeypatch):
    """K = 1 and 3: the field reads ``fold(x + alpha eps_k)`` into [-1, 1]^3 (``eps`` ``[K, N, 3]``
    from the SP seed); the surface/off-surface terms get the mean SDF over the K draws and
    d(mean SDF)/dx through the fold. Kills: the task's field queried plain (``self.sp.blurred(self.field,
    x)`` -> ``self.field(x)``), the box passed to SP not the frame's (``bounds=(-1.0, 1.0)``), and the
    gradient taken at the plain point."""
    config = PointCloudSDFConfig(steps=4, surface_batch=24, space_batch=24, hidden=(16,), encoding=tiny_grid,
                                 sp=SPConfig(alpha0=0.35, schedule="constant", seed=SP_SEED, num_samples=k))
    trainer = config.setup(blob_points)
    field = copy.deepcopy(trainer.field)
    trainer.field = Recorder(trainer.field)
    seen = {}
    real = pointcloud.siren_sdf_losses

    def spy(f_surface, g_surface, normals, f_space, g_space, *args):
        seen.update(f=torch.cat([f_surface, f_space]).detach(), g=torch.cat([g_surface, g_space]).detach(), normals=normals)
        return real(f_surface, g_surface, normals, f_space, g_space, *args)

    monkeypatch.setattr(pointcloud, "siren_sdf_losses", spy)
    trainer.step()

    x, idx = batch_of(trainer, config)
    shape = ((k,) if k > 1 else ()) + x.shape
    eps = torch.randn(shape, generator=torch.Generator().manual_seed(SP_SEED)).double()
    q = folded_query(x, 0.35, eps, -1.0, 1.0)
    assert ((q - (x.double() + 0.35 * eps)).abs() > 1e-3).any()  # some queries were folded
    (read,) = trainer.field.inputs
    torch.testing.assert_close(read.double(), q, rtol=0, atol=2e-5)
    torch.testing.assert_close(seen["normals"], trainer.normals[idx])

    xg = x.clone().requires_grad_(True)
    f = field(folded_query(xg, 0.35, eps, -1.0, 1.0).float()).squeeze(-1)
    f = f.mean(0) if k > 1 else f
    (g,) = torch.autograd.grad(f.sum(), xg)
    torch.testing.assert_close(seen["f"], f.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(seen["g"], g, rtol=1e-4, atol=1e-5)
