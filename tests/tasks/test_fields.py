import pytest
import torch

from sp_plugins.tasks.fields import ENCODING_KINDS, EncodingConfig, NeuralField

SMALL = dict(levels=4, log2_table_size=10, base_resolution=4, max_resolution=32, frequencies=4,
             plane_resolution=16, plane_features=4)


@pytest.mark.parametrize("kind", ENCODING_KINDS)
def test_every_encoding_supports_the_eikonal_double_backward(kind):
    torch.manual_seed(0)
    field = NeuralField(EncodingConfig(kind=kind, **SMALL), dim=3, out_dim=1, hidden=(16, 16))
    x = (torch.rand(64, 3) * 2 - 1).requires_grad_(True)
    f = field(x)
    assert f.shape == (64, 1)
    (g,) = torch.autograd.grad(f.sum(), x, create_graph=True)
    (g.norm(dim=-1) - 1).square().mean().backward()
    grads = [p.grad for p in field.parameters() if p.grad is not None]
    assert grads and any(float(gr.abs().sum()) > 0 for gr in grads)


@pytest.mark.parametrize("kind", ["hashgrid", "fourier", "finer"])
def test_two_dimensional_fields_for_images(kind):
    field = NeuralField(EncodingConfig(kind=kind, **SMALL), dim=2, out_dim=3, hidden=(16,), activation="relu",
                        include_input=False, bounds=(0.0, 1.0))
    assert field(torch.rand(10, 2)).shape == (10, 3)


def test_geometric_init_starts_as_a_sphere():
    torch.manual_seed(0)
    field = NeuralField(EncodingConfig(**SMALL), hidden=(64, 64), geometric_init=True, init_radius=0.5)
    dirs = torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    with torch.no_grad():
        inner = field(0.2 * dirs).squeeze(-1)
        outer = field(0.9 * dirs).squeeze(-1)
    assert bool((inner < 0).all()) and bool((outer > 0).all())
    # roughly metric: the value grows by about the distance travelled
    assert float((outer - inner).mean()) == pytest.approx(0.7, rel=0.3)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="kind"):
        NeuralField(EncodingConfig(kind="voxels"))
    with pytest.raises(ValueError, match="include_input"):
        NeuralField(EncodingConfig(**SMALL), geometric_init=True, include_input=False)
    with pytest.raises(ValueError, match="3D only"):
        NeuralField(EncodingConfig(kind="triplane", **SMALL), dim=2)
