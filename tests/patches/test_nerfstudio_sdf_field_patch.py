"""The opt-in tcnn fallback for nerfstudio's SDFField: guards on nerfstudio internals, then a short training run."""

import importlib.metadata
import types

import pytest
import torch

pytest.importorskip("nerfstudio")

from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.fields import sdf_field
from nerfstudio.fields.sdf_field import SDFFieldConfig
from nerfstudio.utils import external

from sp_plugins.encodings import HashGrid
from sp_plugins.patches import nerfstudio_sdf_field as patch


@pytest.fixture
def restore_patch():
    was_installed = patch.torch_tcnn_fallback_installed()
    yield
    if not was_installed:
        patch.uninstall_torch_tcnn_fallback()


def small_config(**kw):
    args = dict(num_layers=2, hidden_dim=32, geo_feat_dim=15, num_layers_color=2, hidden_dim_color=32,
                use_grid_feature=True, num_levels=4, max_res=64, base_res=8, log2_hashmap_size=12,
                features_per_level=2, smoothstep=True, weight_norm=False, inside_outside=False, bias=0.5)
    args.update(kw)
    return SDFFieldConfig(**args)


def build_field(config):
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    return config.setup(aabb=aabb, num_images=2, spatial_distortion=SceneContraction(order=float("inf")))


def test_nerfstudio_internals_match_what_the_patch_replaces():
    """Fails loudly when nerfstudio changes the code the patch relies on."""
    version = importlib.metadata.version("nerfstudio")
    assert version in patch.TESTED_NERFSTUDIO_VERSIONS, (
        f"nerfstudio {version} is not a version the SDFField tcnn fallback was verified against "
        f"({patch.TESTED_NERFSTUDIO_VERSIONS}): re-check nerfstudio/fields/sdf_field.py and update the patch"
    )
    assert patch.check_nerfstudio_sdf_field() == version
    assert hasattr(sdf_field, "tcnn"), "sdf_field no longer imports tcnn as a module global"


def test_sdf_field_needs_the_patch_without_tcnn(restore_patch):
    if external.TCNN_EXISTS:
        pytest.skip("tcnn is installed")
    patch.uninstall_torch_tcnn_fallback()
    with pytest.raises((RuntimeError, AttributeError)):  # nerfstudio's lazy error object
        build_field(small_config())


def test_install_builds_torch_hashgrid_from_the_fields_config(restore_patch):
    assert patch.install_torch_tcnn_fallback() is True
    assert patch.install_torch_tcnn_fallback() is True  # idempotent
    config = small_config()
    field = build_field(config)
    assert isinstance(field.encoding, HashGrid) and field.encoding.backend == "torch"
    enc = field.encoding
    assert enc.num_levels == 4 and enc.n_output_dims == 8 and enc.interpolation == "Smoothstep"
    assert enc.levels[-1].resolution == 64 and enc.log2_hashmap_size == 12
    with pytest.raises(RuntimeError, match="only provides tcnn.Encoding"):
        sdf_field.tcnn.Network  # noqa: B018


def test_patched_sdf_field_trains(restore_patch):
    """Fit a sphere SDF through forward_geonetwork with an eikonal term (double backward through the grid)."""
    patch.install_torch_tcnn_fallback()
    torch.manual_seed(0)
    field = build_field(small_config())  # geometric init: the grid gets gradients from step 2 on
    table_before = field.encoding.table.detach().clone()
    opt = torch.optim.Adam(field.parameters(), lr=5e-3)
    losses = []
    for _ in range(40):
        x = (torch.rand(512, 3) * 2 - 1).requires_grad_(True)
        sdf = field.forward_geonetwork(x)[:, :1]
        (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=True)
        target = x.norm(dim=-1, keepdim=True) - 0.5
        loss = (sdf - target).abs().mean() + 0.1 * (grad.norm(dim=-1) - 1).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert (field.encoding.table - table_before).abs().max() > 1e-3
    assert sum(losses[-5:]) / 5 < 0.5 * sum(losses[:5]) / 5


def test_patched_sdf_field_get_outputs(restore_patch):
    patch.install_torch_tcnn_fallback()
    field = build_field(small_config(geometric_init=False))
    n_rays, n_samples = 4, 6
    origins = torch.zeros(n_rays, n_samples, 3)
    directions = torch.nn.functional.normalize(torch.randn(n_rays, 1, 3), dim=-1).expand(n_rays, n_samples, 3)
    starts = torch.linspace(0.1, 0.9, n_samples).view(1, n_samples, 1).expand(n_rays, n_samples, 1)
    frustums = Frustums(origins=origins, directions=directions, starts=starts, ends=starts + 0.1, pixel_area=torch.ones(n_rays, n_samples, 1))
    samples = RaySamples(frustums=frustums, camera_indices=torch.zeros(n_rays, n_samples, 1, dtype=torch.long), deltas=torch.full((n_rays, n_samples, 1), 0.1))
    out = field.get_outputs(samples, return_alphas=True)
    assert out[FieldHeadNames.RGB].shape == (n_rays, n_samples, 3)
    assert torch.isfinite(out[FieldHeadNames.GRADIENT]).all()
    out[FieldHeadNames.RGB].sum().backward()
    assert field.encoding.table.grad.abs().sum() > 0


def test_real_tcnn_with_cuda_is_left_alone(restore_patch, monkeypatch):
    patch.uninstall_torch_tcnn_fallback()
    sentinel = types.ModuleType("tinycudann")  # what a real tinycudann import binds
    monkeypatch.setattr(sdf_field, "tcnn", sentinel)
    monkeypatch.setattr(external, "TCNN_EXISTS", True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert patch.install_torch_tcnn_fallback() is False
    assert sdf_field.tcnn is sentinel


def test_uninstall_restores_the_original(restore_patch):
    patch.uninstall_torch_tcnn_fallback()
    original = sdf_field.tcnn
    patch.install_torch_tcnn_fallback()
    assert sdf_field.tcnn is not original
    patch.uninstall_torch_tcnn_fallback()
    assert sdf_field.tcnn is original
