"""Exact values of the nerfstudio seam: for a fixed noise draw, what a field reads equals
the paper's ``x + alpha * eps`` folded into the scene box, computed here from the raw draws with
the reference of ``tests/core/test_properties.py`` (not with the library's ``perturb``).

The mutation of ``sp_plugins/nerfstudio/seam.py`` (or of the
model wiring) each test kills is listed in
``bench/results/mutation_study/kills.json``; the important ones are in ``tests/mutations.py``.
"""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.sdf_field import SDFField
from tests.core.test_properties import fold_reference
from torch import nn

from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.nerfstudio.seam import attach_seam, perturbed_samples

LO = torch.tensor([-1.0, -2.0, -0.5])
HI = torch.tensor([2.0, 1.0, 1.5])  # not a cube, not centred: a wrong box or axis shows
BOX = torch.stack([LO, HI])
SEED = 7
TOL = dict(rtol=0, atol=2e-5)


def samples(n_rays=6, n=12, seed=0) -> RaySamples:
    """Rays through the box from outside it: some samples lie outside (they stay as drawn), many
    near a wall (they are folded); bins of different lengths."""
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.5, -0.5, 3.0]).expand(n_rays, n, 3)
    d = F.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.3 * torch.randn(n_rays, 1, 3, generator=g), dim=-1).expand(n_rays, n, 3)
    t = torch.sort(torch.rand(n_rays, n + 1, generator=g), dim=-1).values * 5.0 + 0.5
    starts, ends = t[:, :-1, None], t[:, 1:, None]
    return RaySamples(Frustums(origins=o, directions=d, starts=starts, ends=ends, pixel_area=torch.full((n_rays, n, 1), 1e-3)),
                      camera_indices=torch.zeros(n_rays, n, 1, dtype=torch.long))


def preconditioner(alpha=0.4, boundary="reflect", **config) -> StochasticPreconditioner:
    sp = StochasticPreconditioner(SPConfig(alpha0=alpha, schedule="constant", boundary=boundary, seed=SEED, **config), bounds=BOX)
    sp.set_step(0, 10)
    return sp.train()


def draws(shape, k=1):
    """The K raw Gaussian draws the seeded preconditioner makes, one ``shape`` draw after another."""
    g = torch.Generator().manual_seed(SEED)
    return [torch.randn(shape, generator=g).double() for _ in range(k)]


def reference(x, alpha, eps, boundary="reflect"):
    """The paper's query: ``x + alpha * eps``, folded into the box where ``x`` lies inside it."""
    x = x.double()
    raw = x + alpha * eps
    if boundary == "none":
        return raw
    inside = ((x >= LO.double()) & (x <= HI.double()))
    return torch.where(inside, fold_reference(raw, LO.double(), HI.double()), raw)


def test_positions_are_x_plus_alpha_eps_reflected_into_the_scene_box():
    """The moved samples' positions are ``x + alpha * eps`` reflected into the scene box, for the fixed draw of
    ``eps``."""
    rs = samples()
    x = rs.frustums.get_positions()
    moved = perturbed_samples(rs, preconditioner())
    (eps,) = draws(x.reshape(-1, 3).shape)
    ref = reference(x.reshape(-1, 3), 0.4, eps).view(x.shape)
    inside = ((x >= LO) & (x <= HI)).all(-1)
    assert inside.any() and (~inside).any() and (ref != x.double() + 0.4 * eps.view(x.shape)).any()  # some folded
    torch.testing.assert_close(moved.frustums.get_positions().double(), ref, **TOL)


def test_sdf_fields_read_starts_moved_by_the_offset_computed_at_the_start():
    """SDF fields read ``get_start_positions()``: the start of every bin with a length is exactly the
    reflected ``start + alpha * eps`` and the midpoint moves by that same offset."""
    rs = samples()
    start, mid = rs.frustums.get_start_positions(), rs.frustums.get_positions()
    assert ((rs.frustums.ends - rs.frustums.starts) > 0).all()
    moved = perturbed_samples(rs, preconditioner(), Frustums.get_start_positions)
    (eps,) = draws(start.reshape(-1, 3).shape)
    ref = reference(start.reshape(-1, 3), 0.4, eps).view(start.shape)
    torch.testing.assert_close(moved.frustums.get_start_positions().double(), ref, **TOL)
    torch.testing.assert_close(moved.frustums.get_positions().double(), mid.double() + (ref - start.double()), **TOL)


def test_gaussian_means_move_by_the_offset_and_the_covariance_stays():
    """MipNeRF reads ``get_gaussian_blob()``: its mean is the plain mean plus the exact offset of the
    midpoint, its covariance the plain one, bit for bit."""
    rs = samples()
    x, blob = rs.frustums.get_positions(), rs.frustums.get_gaussian_blob()
    moved = perturbed_samples(rs, preconditioner()).frustums.get_gaussian_blob()
    (eps,) = draws(x.reshape(-1, 3).shape)
    offset = reference(x.reshape(-1, 3), 0.4, eps).view(x.shape) - x.double()
    torch.testing.assert_close(moved.mean.double(), blob.mean.double() + offset, **TOL)
    assert torch.equal(moved.cov, blob.cov)


class Probe(nn.Module):
    """A radiance field that reads midpoints: a fixed nonlinear function of them."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.tensor([[0.3, -1.1, 0.7], [1.3, 0.2, -0.4]]))

    def forward(self, ray_samples, compute_normals=False):
        p = ray_samples.frustums.get_positions()
        return {FieldHeadNames.RGB: torch.sin(p @ self.w.T), "count": torch.ones(1, dtype=torch.long)}


def probe_reference(p):
    return torch.sin(p @ Probe().w.detach().double().T)


class Holder(nn.Module):
    def __init__(self, field) -> None:
        super().__init__()
        self.field = field


def test_k_draws_average_the_field_at_k_exact_offsets():
    """``num_samples`` K = 3: the field's output is the mean of its K outputs at the K consecutive
    draws, each reflected."""
    model = Holder(Probe())
    attach_seam(model, preconditioner(num_samples=3))
    rs = samples()
    x = rs.frustums.get_positions().reshape(-1, 3)
    out = model.field.forward(rs)
    refs = [probe_reference(reference(x, 0.4, eps)) for eps in draws(x.shape, 3)]
    torch.testing.assert_close(out[FieldHeadNames.RGB].reshape(-1, 2).double(), torch.stack(refs).mean(0), **TOL)
    assert int(out["count"]) == 1  # integer outputs are taken from the first draw, not summed


class ArgsProbe(Probe):
    """A field that records the arguments it was called with besides its samples."""

    def forward(self, ray_samples, compute_normals=False, *rest, **extra):
        self.called = (compute_normals, rest, extra)
        return super().forward(ray_samples)


@pytest.mark.parametrize("how", ["positional", "keyword"])
def test_the_field_gets_the_moved_samples_in_their_place_and_its_other_arguments_as_passed(how):
    """``forward(samples, True, "x", flag=1)`` or ``forward(ray_samples=samples, ...)``: the field reads the
    moved samples, exactly, where it was handed the plain ones, and every other argument as given."""
    model = Holder(ArgsProbe())
    attach_seam(model, preconditioner())
    rs = samples()
    x = rs.frustums.get_positions().reshape(-1, 3)
    out = model.field.forward(rs, True, "x", flag=1) if how == "positional" else \
        model.field.forward(ray_samples=rs, compute_normals=True, flag=1)
    (eps,) = draws(x.shape)
    torch.testing.assert_close(out[FieldHeadNames.RGB].reshape(-1, 2).double(), probe_reference(reference(x, 0.4, eps)), **TOL)
    assert model.field.called == ((True, ("x",), {"flag": 1}) if how == "positional" else (True, (), {"flag": 1}))


def test_the_reach_record_keeps_the_first_calls_largest_move_exactly():
    """What the reach check reads: one moved call counted per field call, and the first call's largest
    move ``max |q - x|`` (the origins' shift), kept when later calls draw again."""
    model = Holder(Probe())
    attach_seam(model, preconditioner())
    rs = samples()
    x = rs.frustums.get_positions().reshape(-1, 3)
    model.field.forward(rs)
    (eps,) = draws(x.shape)
    first = float((reference(x, 0.4, eps) - x.double()).abs().max())
    handle = model.field.sp_handle
    assert handle.perturbed_calls == 1 and float(handle.first_move) == pytest.approx(first, abs=2e-5)
    model.field.forward(rs)
    assert handle.perturbed_calls == 2 and float(handle.first_move) == pytest.approx(first, abs=2e-5)


class SDFProbe(SDFField):
    """An SDF field (the seam moves its starts) with an analytic SDF ``|p| - 0.8``: gradient, normals
    and a NeuS-like alpha computed from them, as nerfstudio's ``SDFField.get_outputs`` does."""

    def __init__(self) -> None:
        nn.Module.__init__(self)
        self.scale = nn.Parameter(torch.tensor(5.0))

    def forward(self, ray_samples, compute_normals=False, return_alphas=False):
        p = ray_samples.frustums.get_start_positions()
        sdf = p.norm(dim=-1, keepdim=True) - 0.8
        grad = p / p.norm(dim=-1, keepdim=True)
        return {FieldHeadNames.SDF: sdf, FieldHeadNames.GRADIENT: grad, FieldHeadNames.NORMALS: F.normalize(grad, dim=-1),
                FieldHeadNames.ALPHA: self.get_alpha(ray_samples, sdf, grad)}

    def get_alpha(self, ray_samples, sdf=None, gradients=None):
        return torch.sigmoid(self.scale * sdf) * gradients.norm(dim=-1, keepdim=True)


def test_k_draws_of_an_sdf_field_recompute_normals_and_alpha_from_the_mean():
    """An SDF field's K = 4 draws: SDF and gradient are the means over the K exact offsets taken at
    the starts; normals are the unit mean gradient and alpha is ``get_alpha(mean SDF, mean gradient)``,
    not the means of the per-draw normals and alphas."""
    model = Holder(SDFProbe())
    attach_seam(model, preconditioner(alpha=0.3, num_samples=4))
    rs = samples()
    s = rs.frustums.get_start_positions().reshape(-1, 3)
    out = model.field.forward(rs)
    qs = [reference(s, 0.3, eps) for eps in draws(s.shape, 4)]
    sdf = torch.stack([q.norm(dim=-1, keepdim=True) - 0.8 for q in qs]).mean(0)
    grad = torch.stack([q / q.norm(dim=-1, keepdim=True) for q in qs]).mean(0)
    torch.testing.assert_close(out[FieldHeadNames.SDF].reshape(-1, 1).double(), sdf, **TOL)
    torch.testing.assert_close(out[FieldHeadNames.GRADIENT].reshape(-1, 3).double(), grad, **TOL)
    torch.testing.assert_close(out[FieldHeadNames.NORMALS].reshape(-1, 3).double(), F.normalize(grad, dim=-1), **TOL)
    alpha = torch.sigmoid(5.0 * sdf) * grad.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(out[FieldHeadNames.ALPHA].reshape(-1, 1).double(), alpha, **TOL)
    assert (grad.norm(dim=-1) < 0.999).any()  # the mean gradient is not a unit vector: a mean of normals differs


class NormalsProbe(Probe):
    """A radiance field that predicts normals (as nerfacto's ``predict_normals``) and has no gradient
    head: after K draws its normals are the mean of its K outputs, as for any other head."""

    def forward(self, ray_samples, compute_normals=False):
        p = ray_samples.frustums.get_positions()
        return {FieldHeadNames.RGB: torch.sin(p @ self.w.T), FieldHeadNames.NORMALS: F.normalize(p, dim=-1)}


def test_k_draws_of_predicted_normals_without_a_gradient_are_the_mean_of_the_draws():
    """Only fields with a gradient head get their normals recomputed after averaging; a field that
    predicts normals keeps the mean of its K = 2 draws (not re-normalised, no KeyError)."""
    model = Holder(NormalsProbe())
    attach_seam(model, preconditioner(num_samples=2))
    rs = samples()
    x = rs.frustums.get_positions().reshape(-1, 3)
    out = model.field.forward(rs)
    qs = [reference(x, 0.4, eps) for eps in draws(x.shape, 2)]
    normals = torch.stack([F.normalize(q, dim=-1) for q in qs]).mean(0)
    assert set(out) == {FieldHeadNames.RGB, FieldHeadNames.NORMALS}
    torch.testing.assert_close(out[FieldHeadNames.NORMALS].reshape(-1, 3).double(), normals, **TOL)
    torch.testing.assert_close(out[FieldHeadNames.RGB].reshape(-1, 2).double(), torch.stack([probe_reference(q) for q in qs]).mean(0), **TOL)


class SDFProbeNoAlpha(SDFProbe):
    """``SDFProbe`` called without ``return_alphas``: SDF, gradient and normals, no alpha head."""

    def forward(self, ray_samples, compute_normals=False, return_alphas=False):
        out = super().forward(ray_samples)
        del out[FieldHeadNames.ALPHA]
        return out


def test_k_draws_of_an_sdf_field_add_no_alpha_it_did_not_return():
    """Alpha is recomputed from the mean only when the field returned one: the outputs' heads are
    the field's."""
    model = Holder(SDFProbeNoAlpha())
    attach_seam(model, preconditioner(alpha=0.3, num_samples=2))
    rs = samples()
    s = rs.frustums.get_start_positions().reshape(-1, 3)
    out = model.field.forward(rs)
    assert set(out) == {FieldHeadNames.SDF, FieldHeadNames.GRADIENT, FieldHeadNames.NORMALS}
    qs = [reference(s, 0.3, eps) for eps in draws(s.shape, 2)]
    grad = torch.stack([q / q.norm(dim=-1, keepdim=True) for q in qs]).mean(0)
    torch.testing.assert_close(out[FieldHeadNames.NORMALS].reshape(-1, 3).double(), F.normalize(grad, dim=-1), **TOL)


class SDFProbeOwnNormals(SDFProbe):
    """An SDF field whose normals are its own head, not the unit gradient (a plugin's field may)."""

    def forward(self, ray_samples, compute_normals=False, return_alphas=False):
        out = super().forward(ray_samples)
        out[FieldHeadNames.NORMALS] = F.normalize(ray_samples.frustums.get_start_positions() + 1.0, dim=-1)
        return out


def test_one_draw_leaves_every_head_as_the_field_computed_it():
    """K = 1: the outputs are the field's own at the exact moved starts; nothing is recomputed after
    the single draw (the recomputation is for means of K > 1 draws)."""
    model = Holder(SDFProbeOwnNormals())
    attach_seam(model, preconditioner(alpha=0.3))
    rs = samples()
    s = rs.frustums.get_start_positions().reshape(-1, 3)
    out = model.field.forward(rs)
    (eps,) = draws(s.shape)
    q = reference(s, 0.3, eps)
    torch.testing.assert_close(out[FieldHeadNames.NORMALS].reshape(-1, 3).double(), F.normalize(q + 1.0, dim=-1), **TOL)
    torch.testing.assert_close(out[FieldHeadNames.SDF].reshape(-1, 1).double(), q.norm(dim=-1, keepdim=True) - 0.8, **TOL)


def test_gradients_reach_the_input_with_the_folds_sign_and_a_learnable_alpha_grid_exactly():
    """d(w . q)/d origins is ``w`` times +-1 (-1 where the fold mirrored the coordinate), and
    d(w . q)/d (alpha grid) equals the reparameterised ``sum_i w_i * fold'_i * eps_i * d alpha_i / d grid``,
    computed here by autograd through the reference formula on a copy of the grid."""
    sp = preconditioner(alpha=0.0, alpha_grid=True, alpha_grid_init=0.35, alpha_grid_resolution=4)
    with torch.no_grad():
        sp.alpha_grid.set_values(0.1 + 0.5 * torch.rand(4, 4, 4, generator=torch.Generator().manual_seed(3)))
    grid_copy = copy.deepcopy(sp.alpha_grid).double()
    rs = samples()
    origins = rs.frustums.origins.clone().requires_grad_(True)
    rs.frustums.origins = origins
    x = rs.frustums.get_positions().detach().reshape(-1, 3)
    w = torch.randn(x.shape, generator=torch.Generator().manual_seed(4))
    q = perturbed_samples(rs, sp).frustums.get_positions().reshape(-1, 3)
    (w * q).sum().backward()

    (eps,) = draws(x.shape)
    ref = reference(x, grid_copy(x.double()), eps)
    torch.testing.assert_close(q.detach().double(), ref, **TOL)
    (w.double() * ref).sum().backward()
    torch.testing.assert_close(sp.alpha_grid.param.grad.double(), grid_copy.param.grad, rtol=1e-4, atol=1e-5)
    raw = x.double() + grid_copy(x.double()).detach() * eps
    u = torch.remainder((raw - LO.double()) / (HI - LO).double(), 2.0)
    inside = (x >= LO) & (x <= HI)
    sign = torch.where(inside & (u > 1.0), -1.0, 1.0)
    assert (sign < 0).any()
    torch.testing.assert_close(origins.grad.reshape(-1, 3).double(), w.double() * sign, **TOL)


def model_of(name: str, **sp):
    """``name`` as its method config builds it (tiny), over the off-centre, non-cubic ``BOX``."""
    from nerfstudio.data.scene_box import SceneBox
    from tests.helpers.ns_configs import shrink_radiance_model

    from sp_plugins.nerfstudio.runs import method_config

    config = method_config(name)
    shrink_radiance_model(name, config)
    for key, value in dict(dict(seed=SEED, schedule="constant", boundary="reflect"), **sp).items():
        setattr(config.pipeline.model.sp, key, value)
    model = config.pipeline.model.setup(scene_box=SceneBox(aabb=BOX.clone()), num_train_data=4, metadata={}, device="cpu",
                                        grad_scaler=None)
    model.sp.set_step(0, 10)
    return model.train()


@pytest.mark.parametrize("name", ["sp-vanilla-nerf", "sp-mipnerf"])
def test_a_models_field_reads_x_plus_alpha0_times_the_box_diagonal_eps_folded_into_its_scene_box(name):
    """The model wiring: with ``relative_to_diagonal`` the field's encoding reads (positions, or
    MipNeRF's Gaussian means) ``x + alpha0 * |diagonal of the scene box| * eps`` folded into that
    scene box."""
    from sp_plugins.nerfstudio.seam import seam_fields

    model = model_of(name, alpha0=0.05, relative_to_diagonal=True)
    (_, field), *_ = seam_fields(model)
    read = []
    field.position_encoding.register_forward_pre_hook(lambda module, args: read.append(args[0].detach().clone()))
    rs = samples()
    x = rs.frustums.get_positions().reshape(-1, 3)
    field.forward(rs)
    (eps,) = draws(x.shape)
    diagonal = float((HI - LO).norm())
    offset = reference(x, 0.05 * diagonal, eps) - x.double()
    plain = rs.frustums.get_gaussian_blob().mean.reshape(-1, 3) if name == "sp-mipnerf" else x
    torch.testing.assert_close(read[0].reshape(-1, 3).double(), plain.double() + offset, **TOL)


def test_a_numerical_gradient_stencil_sits_around_the_moved_start_with_one_offset():
    """``sp-neuralangelo-lite`` (numerical gradients): the SDF network is queried at the moved start
    ``fold(start + alpha eps)`` in the scene box, then at that point +- step e_i for every sample:
    all six stencil points share the one offset."""
    from nerfstudio.data.scene_box import SceneBox
    from tests.helpers.ns_configs import shrink_sdf_model

    from sp_plugins.nerfstudio.runs import method_config

    config = method_config("sp-neuralangelo-lite")
    shrink_sdf_model(config)
    for key, value in dict(seed=SEED, schedule="constant", boundary="reflect", alpha0=0.3, relative_to_diagonal=False).items():
        setattr(config.pipeline.model.sp, key, value)
    model = config.pipeline.model.setup(scene_box=SceneBox(aabb=BOX.clone()), num_train_data=4, metadata={}, device="cpu",
                                        grad_scaler=None)
    model.sp.set_step(0, 10)
    model.train()
    field = model.field
    assert field.config.numerical_gradients and field.config.stencil == "6pt"
    calls = []
    real = field.forward_geonetwork
    field.forward_geonetwork = lambda x: (calls.append(x.detach().clone()), real(x))[1]
    rs = samples()
    field.forward(rs)
    s = rs.frustums.get_start_positions().reshape(-1, 3)
    (eps,) = draws(s.shape)
    centre = reference(s, 0.3, eps)
    torch.testing.assert_close(calls[0].double(), centre, **TOL)
    eye = torch.eye(3, dtype=torch.float64)
    stencil = centre[:, None, :] + field._fd_step * torch.cat([eye, -eye])[None]
    torch.testing.assert_close(calls[1].reshape(-1, 6, 3).double(), stencil, **TOL)
