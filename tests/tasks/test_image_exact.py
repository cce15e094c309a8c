"""Exact values of the image-fitting task (issue 44): in one step with the learnable alpha map the
field is queried at ``p + alpha_map(p) * eps`` (K draws averaged) folded into the image square
``[0, 1]^2``, and the gradient reaching the alpha map is the reparameterised ``eps``-weighted value,
computed here by autograd through the paper's formula on copies of the field and the map.
Each test names the mutation of ``sp_plugins/tasks/image.py`` / the core it kills."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.image import ImageFitConfig
from tests.helpers.exact import Recorder, folded_query

H, W, SP_SEED = 6, 8, 9


def pixel_centres() -> torch.Tensor:
    """``(x, y)`` of the pixel centres in [0, 1]^2, row-major (written here, not the task's helper)."""
    return torch.tensor([[(j + 0.5) / W, (i + 0.5) / H] for i in range(H) for j in range(W)])


@pytest.mark.parametrize("k", [1, 2])
def test_one_step_queries_p_plus_the_maps_alpha_eps_and_the_map_gets_the_eps_weighted_gradient(k):
    """K = 1 and 2: the field reads ``fold(p + alpha_map(p) * eps_k)`` into [0, 1]^2 at every pixel
    centre, and d loss / d (alpha map) equals autograd through that formula with the mean colour
    over the K draws. Kills: the map's gradient cut (``alpha_grid(x.detach()).detach()``), the map
    not attached (``self.sp.alpha_grid = ...`` dropped: the scalar alpha used), the image square
    not the SP box (``bounds=(0.0, 1.0)``) and the K-draw average dropped."""
    image = np.random.default_rng(0).random((H, W, 3)).astype(np.float32)
    config = ImageFitConfig(steps=10, batch=4096, hidden=(16,), adaptive_alpha=True, alpha_map_downscale=2,
                            encoding=EncodingConfig(levels=3, log2_table_size=8, base_resolution=2, max_resolution=8),
                            sp=SPConfig(alpha0=0.2, schedule="constant", seed=SP_SEED, num_samples=k))
    trainer = config.setup(image)
    with torch.no_grad():  # a map that is not constant: which cell a pixel reads matters
        values = 0.05 + 0.4 * torch.rand(trainer.sp.alpha_grid.values().shape, generator=torch.Generator().manual_seed(1))
        trainer.sp.alpha_grid.set_values(values)
    field, grid = copy.deepcopy(trainer.field), copy.deepcopy(trainer.sp.alpha_grid)
    trainer.field = Recorder(trainer.field)
    trainer.step()

    p = pixel_centres()
    shape = ((k,) if k > 1 else ()) + p.shape
    eps = torch.randn(shape, generator=torch.Generator().manual_seed(SP_SEED)).double()
    alpha = grid(p)
    q = folded_query(p, alpha, eps, 0.0, 1.0)
    assert ((q - (p.double() + alpha.detach() * eps)).abs() > 1e-3).any()  # some queries were folded
    (read,) = trainer.field.inputs
    torch.testing.assert_close(read.double(), q.detach(), rtol=0, atol=2e-5)

    rgb = torch.sigmoid(field(q.float()))
    rgb = rgb.mean(0) if k > 1 else rgb
    loss = (rgb - torch.from_numpy(image.reshape(-1, 3))).square().mean()
    loss.backward()
    assert grid.param.grad.abs().max() > 0
    torch.testing.assert_close(trainer.sp.alpha_grid.param.grad, grid.param.grad, rtol=1e-4, atol=1e-7)
    assert trainer.history["loss"][0] == pytest.approx(float(loss), rel=1e-5)
