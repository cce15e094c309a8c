"""Frequency (with the integrated variance term) and triplane encodings."""

import math

import pytest
import torch
import torch.nn.functional as F

from sp_plugins.encodings import FrequencyEncoding, TriplaneEncoding


def test_frequency_features_closed_form():
    enc = FrequencyEncoding(n_input_dims=2, num_frequencies=3, min_freq_exp=0, max_freq_exp=2, include_input=True)
    x = torch.rand(5, 2, dtype=torch.float64)
    out = enc(x)
    assert out.shape == (5, enc.n_output_dims) == (5, 2 * 2 * 3 + 2)
    w = 2 * math.pi * torch.tensor([1.0, 2.0, 4.0], dtype=torch.float64)
    phase = torch.cat([w[k] * x for k in range(3)], dim=-1)
    torch.testing.assert_close(out, torch.cat([phase.sin(), phase.cos(), x], dim=-1))


def test_integrated_encoding_is_the_gaussian_average():
    """E over x + alpha * N(0, I) of the plain encoding equals the encoding with variance alpha^2."""
    torch.manual_seed(0)
    enc = FrequencyEncoding(n_input_dims=3, num_frequencies=4, min_freq_exp=-2, max_freq_exp=1)
    x = torch.rand(4, 3, dtype=torch.float64)
    alpha = torch.tensor([0.02, 0.05, 0.1], dtype=torch.float64)
    samples = x + alpha * torch.randn(200_000, 1, 3, dtype=torch.float64)
    monte_carlo = enc(samples).mean(0)
    integrated = enc(x, variance=alpha.square().expand(4, 3))
    plain = enc(x)
    torch.testing.assert_close(integrated, monte_carlo, atol=6e-3, rtol=0)
    assert (plain - monte_carlo).abs().max() > 0.1  # the variance term matters at these alphas
    cov = torch.diag_embed(alpha.square().expand(4, 3))
    torch.testing.assert_close(enc(x, variance=cov), integrated)


def test_frequency_gradients():
    enc = FrequencyEncoding(num_frequencies=2)
    x = torch.rand(3, 3, dtype=torch.float64, requires_grad=True)
    var = torch.rand(3, 3, dtype=torch.float64, requires_grad=True) * 1e-3
    assert torch.autograd.gradcheck(enc, (x, var))
    assert torch.autograd.gradgradcheck(enc, (x, var))


def test_frequency_bad_input():
    with pytest.raises(ValueError, match="max_freq_exp"):
        FrequencyEncoding(min_freq_exp=3, max_freq_exp=1)
    with pytest.raises(ValueError, match="variance"):
        FrequencyEncoding()(torch.rand(2, 3), variance=torch.rand(2, 2))


@pytest.mark.parametrize("reduce", ["sum", "product", "concat"])
def test_triplane_matches_grid_sample(reduce):
    torch.manual_seed(0)
    enc = TriplaneEncoding(resolution=9, channels=4, reduce=reduce).double()
    x = torch.rand(100, 3, dtype=torch.float64)
    planes = enc.planes.detach().permute(0, 3, 2, 1)  # [P, C, H=j(v), W=i(u)]
    ref = []
    for p, (a, b) in enumerate([(0, 1), (0, 2), (1, 2)]):
        coords = (x[:, [a, b]] * 2 - 1).view(1, -1, 1, 2)
        ref.append(F.grid_sample(planes[p : p + 1], coords, align_corners=True).view(4, -1).T)
    ref = torch.stack(ref)
    expected = {"sum": ref.sum(0), "product": ref.prod(0), "concat": ref.permute(1, 0, 2).reshape(100, 12)}[reduce]
    torch.testing.assert_close(enc(x), expected)


def test_triplane_derivatives_wrt_inputs_and_planes():
    torch.manual_seed(0)
    enc = TriplaneEncoding(resolution=5, channels=2, reduce="product").double()
    x = (torch.rand(6, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    planes = enc.planes.detach().clone().requires_grad_(True)

    def f(x, planes):
        return torch.func.functional_call(enc, {"planes": planes}, (x,))

    assert torch.autograd.gradcheck(f, (x, planes))
    assert torch.autograd.gradgradcheck(f, (x, planes))
    (g,) = torch.autograd.grad(enc(x).sum(), x)
    assert g.abs().min() > 0  # unlike nerfstudio's triplane, inputs get gradients


def test_triplane_bad_reduce():
    with pytest.raises(ValueError, match="reduce"):
        TriplaneEncoding(reduce="max")
