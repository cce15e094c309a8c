import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.core import finite_differences, stencil_offsets


def field(p):
    x, y, z = p.unbind(-1)
    return x**2 + torch.sin(y) + x * y * z


def analytic(p):
    x, y, z = p.unbind(-1)
    grad = torch.stack([2 * x + y * z, torch.cos(y) + x * z, x * y], -1)
    lap = 2 - torch.sin(y)
    return grad, lap


@pytest.mark.parametrize("kind, tol", [("6pt", 1e-6), ("4pt", 2e-3)])
def test_stencil_gradient_and_laplacian_match_analytic(kind, tol):
    p = torch.rand(64, 3, dtype=torch.float64) * 2 - 1
    grad, lap = finite_differences(field, p, 1e-3, kind, centre_values=field(p))
    g_true, l_true = analytic(p)
    assert torch.allclose(grad, g_true, atol=tol)
    assert torch.allclose(lap, l_true, atol=1e-3 if kind == "6pt" else 5e-3)


def test_tetrahedral_stencil_is_balanced():
    v = stencil_offsets("4pt", dtype=torch.float64)
    assert torch.allclose(v.sum(0), torch.zeros(3, dtype=torch.float64))
    assert torch.allclose(v.T @ v, 4 * torch.eye(3, dtype=torch.float64))


def test_stencil_around_a_perturbed_centre_shares_one_offset():
    """With one offset per sample, the stencil of a linear field recovers its slope exactly,
    however large alpha is: the noise moves the whole stencil, not its points apart."""
    a = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)
    lin = lambda p: p @ a  # noqa: E731
    sp = SPConfig(alpha0=0.5, schedule="constant", boundary="none").setup(total_steps=10)
    centres = sp(torch.rand(500, 3, dtype=torch.float64))
    grad, _ = finite_differences(lin, centres, 1e-2, "6pt")
    assert torch.allclose(grad, a.expand_as(grad), atol=1e-9)
    # whereas perturbing each stencil point separately would wreck the estimate
    from sp_plugins.core import stencil_gradient, stencil_points

    pts = sp(stencil_points(centres, 1e-2, "6pt"))
    noisy = stencil_gradient(lin(pts), 1e-2, "6pt")
    assert float((noisy - a).abs().mean()) > 1.0


def test_unknown_stencil_is_rejected():
    with pytest.raises(ValueError, match="stencil"):
        stencil_offsets("5pt")


def test_offsets_are_made_once_per_device_and_dtype(monkeypatch):
    """``torch.tensor(list, device=cuda)`` is a blocking host-to-device copy: not once per call."""
    first = stencil_offsets("4pt", dtype=torch.float64)
    made = []
    real = torch.tensor
    monkeypatch.setattr(torch, "tensor", lambda *a, **k: made.append(a) or real(*a, **k))
    assert stencil_offsets("4pt", dtype=torch.float64) is first
    with torch.inference_mode():
        inside = stencil_offsets("4pt", dtype=torch.float16)
    assert not inside.is_inference()  # a tensor made under inference mode could not be saved for backward later
    assert stencil_offsets("4pt", dtype=torch.float16) is inside and len(made) == 1
