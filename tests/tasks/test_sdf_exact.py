"""Exact values of the direct SDF-fitting task (issue 44): in one step the field is queried at the
paper's ``x + alpha * eps`` (K draws averaged) folded into the frame's box ``[-1, 1]^3``, and the
loss is the MAPE of that (mean) prediction against the plain points' distances, computed here
from the raw seeded draws. Each test names the mutation of ``sp_plugins/tasks/sdf.py`` it kills."""

from __future__ import annotations

import copy

import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.tasks.sdf import SDFFitConfig
from tests.helpers.exact import Recorder, folded_query

SP_SEED = 4


@pytest.mark.parametrize("k", [1, 3])
def test_one_step_queries_x_plus_alpha_eps_and_fits_the_mean_to_the_plain_distances(k, blob_mesh, tiny_grid):
    """K = 1 and 3: the batch (half surface, a quarter near, a quarter uniform points, drawn from the batch generator) is
    read at ``fold(x + alpha eps_k)`` into [-1, 1]^3 and the loss is MAPE(mean prediction, d(x)).
    Kills: the field queried plain (``self.sp.blurred(self.field, x)`` -> ``self.field(x)``), the
    targets taken at the moved points, the box not the frame's and the K-draw average dropped."""
    config = SDFFitConfig(steps=4, batch=40, pool=400, hidden=(16,), encoding=tiny_grid,
                          sp=SPConfig(alpha0=0.3, schedule="constant", seed=SP_SEED, num_samples=k))
    trainer = config.setup(blob_mesh)
    field = copy.deepcopy(trainer.field)
    trainer.field = Recorder(trainer.field)
    trainer.step()

    g = torch.Generator().manual_seed(config.seed)
    xs, ds = [], []
    for (pts, dist), n in zip(trainer.groups, (20, 10, 10)):
        idx = torch.randint(len(pts), (n,), generator=g)
        xs.append(pts[idx])
        ds.append(dist[idx])
    x, d = torch.cat(xs), torch.cat(ds)
    shape = ((k,) if k > 1 else ()) + x.shape
    eps = torch.randn(shape, generator=torch.Generator().manual_seed(SP_SEED)).double()
    q = folded_query(x, 0.3, eps, -1.0, 1.0)
    assert ((q - (x.double() + 0.3 * eps)).abs() > 1e-3).any()  # some queries were folded
    (read,) = trainer.field.inputs
    torch.testing.assert_close(read.double(), q, rtol=0, atol=2e-5)
    with torch.no_grad():
        pred = field(q.float()).squeeze(-1)
        pred = pred.mean(0) if k > 1 else pred
    loss = ((pred - d).abs() / (d.abs() + 0.01)).mean()
    assert trainer.history["loss"][0] == pytest.approx(float(loss), rel=1e-5)
