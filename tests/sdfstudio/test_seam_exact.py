"""Exact values of the sdfstudio seam: for a fixed noise draw, the SDF field is queried
at the paper's ``x + alpha * eps`` taken in sdfstudio's contracted space and folded into the
contraction's range ``[-2, 2]^3``, computed here from the raw draws with the reference fold of
``tests/core/test_properties.py`` and a contraction written here (not the library's ``perturb`` or
the host's ``SceneContraction``).

The mutation each test kills is listed in ``bench/results/mutation_study/kills.json``; the important ones are in
``tests/mutations.py``.
"""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from tests.core.test_properties import fold_reference
from tests.sdfstudio.test_seam import Spy, tiny_field

pytestmark = pytest.mark.usefixtures("patched")

SEED = 11
N_RAYS, N_SAMPLES = 5, 8
TOL = dict(rtol=0, atol=2e-5)


def contract(x: torch.Tensor) -> torch.Tensor:
    """sdfstudio's scene contraction (inf-norm): identity inside the unit cube, ``(2 - 1/|x|) x/|x|`` outside."""
    mag = x.abs().max(dim=-1, keepdim=True).values
    return torch.where(mag >= 1, (2 - 1 / mag) * x / mag, x)


def ray_samples():
    """Rays from (0.3, -0.2, 3) towards -z: samples inside the unit box (contraction the identity),
    beyond it (contracted), and far away, close to the contracted range's wall at 2 (folded)."""
    from nerfstudio.cameras.rays import Frustums, RaySamples

    g = torch.Generator().manual_seed(2)
    origins = torch.tensor([0.3, -0.2, 3.0]).expand(N_RAYS, N_SAMPLES, 3).contiguous()
    directions = F.normalize(torch.randn(N_RAYS, 1, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    directions = directions.expand(N_RAYS, N_SAMPLES, 3).contiguous()
    starts = torch.tensor([0.5, 2.2, 2.8, 3.3, 4.5, 9.0, 40.0, 200.0]).view(1, N_SAMPLES, 1).expand(N_RAYS, N_SAMPLES, 1).contiguous()
    frustums = Frustums(origins=origins, directions=directions, starts=starts, ends=starts + 0.1, pixel_area=torch.ones_like(starts))
    return RaySamples(frustums=frustums, camera_indices=torch.zeros(N_RAYS, N_SAMPLES, 1, dtype=torch.long),
                      deltas=torch.full_like(starts, 0.1))


def preconditioner(alpha=0.15, **config):
    from sp_plugins.core import SPConfig
    from sp_plugins.sdfstudio.seam import CONTRACTED_BOUNDS

    sp = SPConfig(alpha0=alpha, schedule="constant", seed=SEED, **config).setup(bounds=CONTRACTED_BOUNDS)
    sp.set_step(0)
    return sp.train()


def reference(x: torch.Tensor, alpha, lo=-2.0, hi=2.0) -> torch.Tensor:
    """``contract(x) + alpha * eps`` folded into ``[lo, hi]^3``, ``eps`` the seeded preconditioner's draw."""
    c = contract(x.double())
    eps = torch.randn(c.shape, generator=torch.Generator().manual_seed(SEED)).double()
    return fold_reference(c + alpha * eps, torch.tensor(lo).double(), torch.tensor(hi).double())


def starts(samples) -> torch.Tensor:
    return samples.frustums.get_start_positions().reshape(-1, 3)


def test_the_query_is_the_contracted_start_plus_alpha_eps_folded_into_the_contracted_range_and_the_stencil_shares_it():
    """The centre query of every sample is ``fold(contract(start) + alpha * eps)`` into ``[-2, 2]^3``,
    and the six stencil points are that centre +- delta e_i exactly."""
    field, sp = tiny_field(numerical=True, fd_step=0.01), preconditioner()
    field.use_preconditioner(sp)
    field.train()
    spy, samples = Spy(field), ray_samples()
    field(samples, return_alphas=True)
    centre, stencil = spy.calls
    ref = reference(starts(samples), 0.15)
    c = contract(starts(samples).double())
    raw = c + 0.15 * torch.randn(c.shape, generator=torch.Generator().manual_seed(SEED)).double()
    assert ((raw - ref).abs() > 1e-3).any() and (c.abs() > 1).any()  # some queries folded, some contracted
    torch.testing.assert_close(centre.double(), ref, **TOL)
    eye = torch.eye(3, dtype=torch.float64)
    steps = torch.stack([eye[0], -eye[0], eye[1], -eye[1], eye[2], -eye[2]])[:, None, :] * 0.01
    torch.testing.assert_close(stencil.view(6, -1, 3).double(), ref[None] + steps, **TOL)


def test_queries_fold_at_both_walls_of_the_contracted_range():
    """The same rays mirrored (towards +z): far samples contract towards the upper wall at +2 and
    fold there, exactly as the reference folds into ``[-2, 2]^3``."""
    import dataclasses

    field, sp = tiny_field(numerical=False), preconditioner()
    field.use_preconditioner(sp)
    field.train()
    samples = ray_samples()
    f = samples.frustums
    mirrored = dataclasses.replace(f, origins=f.origins * torch.tensor([1.0, 1.0, -1.0]), directions=f.directions * torch.tensor([1.0, 1.0, -1.0]))
    samples = dataclasses.replace(samples, frustums=mirrored)
    spy = Spy(field)
    field(samples)
    ref = reference(starts(samples), 0.15)
    c = contract(starts(samples).double())
    raw = c + 0.15 * torch.randn(c.shape, generator=torch.Generator().manual_seed(SEED)).double()
    assert (raw > 2.0).any() and ((raw - ref).abs() > 1e-3).any()  # some queries folded at the upper wall
    torch.testing.assert_close(spy.calls[0].double(), ref, **TOL)


def test_the_eikonal_gradient_is_taken_at_the_reference_point():
    """With autograd normals the field's gradient is d sdf / d q at ``q = fold(contract(x) + alpha eps)``."""
    from nerfstudio.field_components.field_heads import FieldHeadNames

    field, sp = tiny_field(numerical=False), preconditioner()
    field.use_preconditioner(sp)
    field.train()
    samples = ray_samples()
    out = field(samples)
    q = reference(starts(samples), 0.15).float().requires_grad_(True)
    (expected,) = torch.autograd.grad(field.forward_geonetwork(q)[:, :1].sum(), q)
    torch.testing.assert_close(out[FieldHeadNames.GRADIENT].reshape(-1, 3), expected, rtol=1e-4, atol=1e-5)


def test_the_reach_record_counts_each_moved_query_and_keeps_the_first_move_exactly():
    """What the reach check reads: one moved contraction call per training query, and the first
    query's largest move ``max |fold(c + alpha eps) - c|``, kept (a later query does not replace it);
    the model's check then passes."""
    from torch import nn

    from sp_plugins.sdfstudio.seam import check_reached

    field, sp = tiny_field(numerical=False), preconditioner()
    field.use_preconditioner(sp)
    field.train()
    samples = ray_samples()
    field(samples)
    c = contract(starts(samples).double())
    first = float((reference(starts(samples), 0.15) - c).abs().max())
    assert field.sp_handle.perturbed_calls == 1
    assert float(field.sp_handle.first_move) == pytest.approx(first, abs=2e-5)
    field(samples)
    assert field.sp_handle.perturbed_calls == 2 and float(field.sp_handle.first_move) == pytest.approx(first, abs=2e-5)
    model = nn.Module()
    model.field = field
    check_reached(model, "NeuSModel", 0)


def test_the_samplers_queries_are_the_hosts_at_the_plain_starts_or_when_asked_at_the_moved_ones():
    """``get_sdf`` (NeuS up-sampling) and ``get_density`` (VolSDF's sampler) while training: by default
    exactly sdfstudio's own ``SDFField`` methods; with ``perturb_sampler_queries`` the same computation
    at ``fold(start + alpha eps)`` (no contraction: the host's samplers query uncontracted starts)."""
    from nerfstudio.fields.sdf_field import SDFField

    from tests.helpers.exact import folded_query

    field = tiny_field(numerical=False)
    field.use_preconditioner(preconditioner())
    field.train()
    samples = ray_samples()
    assert torch.equal(field.get_sdf(samples), SDFField.get_sdf(field, samples))
    density, feature = field.get_density(samples)
    host_density, host_feature = SDFField.get_density(field, samples)
    assert torch.equal(density, host_density) and torch.equal(feature, host_feature)

    field.config.perturb_sampler_queries = True
    x = starts(samples)
    q = folded_query(x, 0.15, torch.randn(x.shape, generator=torch.Generator().manual_seed(SEED)).double(), -2.0, 2.0).float()
    hidden = field.forward_geonetwork(q).view(N_RAYS, N_SAMPLES, -1)
    field.use_preconditioner(preconditioner())  # a fresh draw of the seed for each query
    torch.testing.assert_close(field.get_sdf(samples), hidden[..., :1], **TOL)
    field.use_preconditioner(preconditioner())
    density, feature = field.get_density(samples)
    torch.testing.assert_close(density, field.laplace_density(hidden[..., :1]), **TOL)
    torch.testing.assert_close(feature, hidden[..., 1:], **TOL)


def test_the_alpha_grid_gradient_through_the_contraction_is_the_eps_weighted_value():
    """A learnable alpha grid over the contracted range: d(sum sdf)/d(grid) equals autograd through
    ``fold(c + alpha_grid(c) * eps)``, ``c = contract(x)``, on a copy of the grid."""
    from nerfstudio.field_components.field_heads import FieldHeadNames

    field, sp = tiny_field(numerical=False), preconditioner(alpha=0.0, alpha_grid=True, alpha_grid_init=0.1, alpha_grid_resolution=4)
    with torch.no_grad():
        sp.alpha_grid.set_values(0.05 + 0.2 * torch.rand(4, 4, 4, generator=torch.Generator().manual_seed(3)))
    grid = copy.deepcopy(sp.alpha_grid)
    field.use_preconditioner(sp)
    field.train()
    samples = ray_samples()
    field(samples)[FieldHeadNames.SDF].sum().backward()
    c = contract(starts(samples))
    eps = torch.randn(c.shape, generator=torch.Generator().manual_seed(SEED))
    q = fold_reference(c + grid(c) * eps, torch.tensor(-2.0), torch.tensor(2.0))
    field.forward_geonetwork(q)[:, :1].sum().backward()
    assert grid.param.grad.abs().max() > 0
    torch.testing.assert_close(sp.alpha_grid.param.grad, grid.param.grad, rtol=1e-4, atol=1e-6)


def neus_model(**sp):
    """sdfstudio's NeuS model as ``sp-neus`` builds it (tiny field), over a non-unit scene box."""
    import nerfstudio.configs.method_configs as methods
    from nerfstudio.data.scene_box import SceneBox

    config = copy.deepcopy(methods.method_configs["sp-neus"].pipeline.model)
    f = config.sdf_field
    f.num_layers, f.hidden_dim, f.geo_feat_dim, f.hidden_dim_color = 2, 32, 15, 32
    f.num_levels, f.log2_hashmap_size, f.base_res, f.max_res = 4, 11, 8, 64
    config.background_model = "none"
    for key, value in dict(dict(seed=SEED, schedule="constant"), **sp).items():
        setattr(config.sp, key, value)
    aabb = torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])
    return config.setup(scene_box=SceneBox(aabb=aabb), num_train_data=2, world_size=1, local_rank=0)


def test_the_model_folds_into_the_contracted_range_with_alpha_relative_to_the_scene_diagonal():
    """``sp-neus`` with ``relative_to_diagonal``: the field queries ``fold(contract(x) + alpha0 *
    diagonal * eps)`` into ``[-2, 2]^3``, the diagonal the scene box's (3 sqrt 3 here)."""
    model = neus_model(alpha0=0.03, relative_to_diagonal=True)
    model.sp.set_step(0, 10)
    model.train()
    spy, samples = Spy(model.field), ray_samples()
    model.field(samples)
    ref = reference(starts(samples), 0.03 * 3 * 3**0.5)
    torch.testing.assert_close(spy.calls[0].double(), ref, **TOL)


def test_more_than_one_draw_is_refused_naming_the_flag():
    """sdfstudio's seam perturbs each query once (sdfstudio's ``get_outputs`` is not wrapped), so
    ``num_samples`` K > 1 cannot average K draws there: the model refuses it (``InputError``), naming
    the flag, instead of training a single draw silently (found by this test: it used to build and
    train K = 1)."""
    from sp_plugins.adapter.errors import InputError

    with pytest.raises(InputError, match=r"--pipeline\.model\.sp\.num-samples 3 .*sdfstudio"):
        neus_model(num_samples=3)


def test_the_read_point_comes_from_the_hosts_table():
    """The seam's field reads its samplers' positions where ``table.READ_POINTS`` says sdfstudio's ``SDFField`` queries
    (the bins' starts), found through its nearest base; a class the table does not name reads ``get_positions``."""
    from nerfstudio.fields.sdf_field import SDFField

    from sp_plugins.sdfstudio import seam, table

    assert table.READ_POINTS == {"nerfstudio.fields.sdf_field.SDFField": "get_start_positions"}
    assert seam.read_point(seam.SeamSDFField) == seam.read_point(SDFField) == "get_start_positions"
    assert seam.read_point(torch.nn.Module) == "get_positions"
