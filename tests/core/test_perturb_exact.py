"""``perturb`` (sp_plugins.core.perturb) on a two-dimensional batch, exactly: positions ``[B, N, dim]`` with a
per-point alpha ``[B, N]`` and a box, equal to the paper's ``x + alpha * eps`` folded into the box, computed here
from the same draws. (``tests/core/test_properties.py`` covers one batch dimension, where ``x.dim() - 1`` is 1
whichever way it is written.) The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

import pytest
import torch

from sp_plugins.core import perturb

from .test_properties import fold_reference


@pytest.mark.parametrize("k", [1, 3])
def test_a_per_point_alpha_on_a_two_dimensional_batch_is_each_points_own(k):
    """``x`` [2, 4, 3] in the box [0, 1]^3, ``alpha`` [2, 4] (one per point, some large enough to fold): the output
    is ``fold(x + alpha[..., None] * eps)`` with ``eps`` the generator's Gaussian draws of ``[K, 2, 4, 3]``."""
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 4, 3, generator=g, dtype=torch.float64)
    alpha = torch.rand(2, 4, generator=g, dtype=torch.float64) * 0.8
    y = perturb(x, alpha, boundary="reflect", bounds=(0.0, 1.0), num_samples=k, generator=torch.Generator().manual_seed(9))
    shape = ((k,) if k > 1 else ()) + (2, 4, 3)
    eps = torch.randn(shape, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    ref = fold_reference(x + alpha[..., None] * eps, torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64))
    assert y.shape == shape
    torch.testing.assert_close(y, ref, rtol=0, atol=1e-12)
