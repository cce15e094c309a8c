"""Exact values of the point cloud -> SDF task: in one training step the field is
queried at the paper's ``x + alpha * eps`` (K draws averaged), folded into the frame's box
``[-1, 1]^3``, and the SIREN terms get the SDF there and its gradient with respect to ``x``
(the perturbed field's: the fold's sign included), computed here from the raw seeded draws.
The mutation of ``sp_plugins/tasks/pointcloud.py`` / ``common.py`` each test kills is listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import copy
import math
import re

import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.tasks import pointcloud
from sp_plugins.tasks.pointcloud import PointCloudSDFConfig
from tests.helpers.exact import (
    Recorder, assert_alpha_grid_frozen_once_sp_ends, assert_keyword_only_options, assert_read_folded, folded_query, sp_draws,
)

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
    d(mean SDF)/dx through the fold."""
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
    eps = sp_draws(x, k, SP_SEED)
    assert_read_folded(trainer, x, 0.35, eps, -1.0, 1.0)
    torch.testing.assert_close(seen["normals"], trainer.normals[idx])

    xg = x.clone().requires_grad_(True)
    f = field(folded_query(xg, 0.35, eps, -1.0, 1.0).float()).squeeze(-1)
    f = f.mean(0) if k > 1 else f
    (g,) = torch.autograd.grad(f.sum(), xg)
    torch.testing.assert_close(seen["f"], f.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(seen["g"], g, rtol=1e-4, atol=1e-5)


# --- the mutation study's survivors in pointcloud.py -------------------------------------

def tiny(grid, **kw) -> PointCloudSDFConfig:
    base = dict(steps=2, surface_batch=16, space_batch=16, hidden=(16,), encoding=grid)
    base.update(kw)
    return PointCloudSDFConfig(**base)


def test_the_defaults_are_the_point_cloud_tables_setting():
    """README: the ``pointcloud`` defaults are the setting of the point-cloud table (docs/results/pointcloud-sdf.md) (2000 steps,
    2500 + 2500 points, 200k samples, SIREN weights 3e3 / 1e2 / 5e1 squared / 1e2, lr 1e-3, 2x64 MLP, output
    bias 0, 192^3 meshing with 4 bisections, 200k metric points, SP 0.03 step to 0 at 20%); the rest as
    their docs say."""
    c = PointCloudSDFConfig()
    assert (c.steps, c.seed, c.lr, c.hidden) == (2000, 0, 1e-3, (64, 64))
    assert (c.surface_batch, c.space_batch, c.n_points) == (2500, 2500, 200_000)
    assert (c.w_surface, c.w_normal, c.w_eikonal, c.w_offsurface) == (3e3, 1e2, 5e1, 1e2)
    assert (c.eikonal, c.offsurface_falloff) == ("squared", 100.0)
    assert (c.output_bias, c.geometric_init, c.include_input, c.init_radius) == (0.0, False, None, 0.5)
    assert (c.lr_final_ratio, c.grad_clip) == (1.0, 1.0)
    assert (c.frame_diagonal, c.mesh_resolution, c.refine, c.metric_points) == (1.9, 192, 4, 200_000)
    assert (c.encoding.levels, c.encoding.log2_table_size, c.encoding.max_resolution) == (16, 16, 1024)
    assert (c.sp.enabled, c.sp.alpha0, c.sp.schedule, c.sp.end) == (True, 0.03, "step", 0.2)
    assert (c.sp.noise, c.sp.boundary) == ("gaussian", "reflect")


SIZES = "steps, surface_batch, space_batch and n_points must be >= 1"


@pytest.mark.parametrize("name, refused, accepted, message", [
    ("steps", 0, 1, SIZES),
    ("surface_batch", 0, 1, SIZES),
    ("space_batch", 0, 1, SIZES),
    ("n_points", 0, 1, SIZES),
    ("lr", 0.0, 1e-12, "lr=0.0, lr_final_ratio=1.0: need lr > 0 and 0 < ratio <= 1"),
    ("lr", -1e-3, 1e-12, "lr=-0.001, lr_final_ratio=1.0: need lr > 0 and 0 < ratio <= 1"),
    ("lr_final_ratio", 0.0, 1.0, "lr=0.001, lr_final_ratio=0.0: need lr > 0 and 0 < ratio <= 1"),
    ("lr_final_ratio", 1.5, 1e-6, "lr=0.001, lr_final_ratio=1.5: need lr > 0 and 0 < ratio <= 1"),
    ("lr_final_ratio", -0.5, 1e-6, "lr=0.001, lr_final_ratio=-0.5: need lr > 0 and 0 < ratio <= 1"),
    ("mesh_resolution", 7, 8, "mesh_resolution=7: use at least 8"),
    ("eikonal", "cubic", "abs", "eikonal='cubic': use 'squared' or 'abs'"),
    ("grad_clip", -1.0, 0.0, "grad_clip=-1.0: use 0 (off) or a positive gradient norm"),
    ("grad_clip", float("nan"), 0.5, "grad_clip=nan: use 0 (off) or a positive gradient norm"),
])
def test_validation_refuses_exactly_the_documented_values_in_one_line(name, refused, accepted, message):
    """Each bound at its edge: the first refused value gives the one line ``sp-fit`` prints (after
    ``sp-fit: error:``), the boundary value is accepted. A negative ``--grad-clip`` was accepted and, through
    ``clip_grad_norm_``, turned every step into gradient ascent; it is refused now."""
    with pytest.raises(ValueError) as refused_error:
        PointCloudSDFConfig(**{name: refused}).validate()
    assert str(refused_error.value) == message
    PointCloudSDFConfig(**{name: accepted}).validate()


def test_the_siren_terms_are_the_papers_formulas_for_both_eikonal_penalties():
    """A hand-made batch: mean |f| on the surface, mean(1 - cos(grad, n)), the mean squared or absolute
    (|grad| - 1) over surface and space points, mean exp(-falloff |f|) off the surface."""
    d = dict(dtype=torch.float64)
    f_surface = torch.tensor([0.1, -0.3], **d)
    g_surface = torch.tensor([[3.0, 0.0, 4.0], [0.0, 0.0, 2.0]], **d)  # |g| 5 and 2
    normals = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], **d)  # cos 0.8 and 0
    f_space = torch.tensor([0.01, -0.02], **d)
    g_space = torch.tensor([[0.0, 1.0, 0.0], [0.5, 0.0, 0.0]], **d)  # |g| 1 and 0.5
    # |g| - 1 = 4, 1, 0, -0.5
    for eikonal, expected in (("squared", (16 + 1 + 0 + 0.25) / 4), ("abs", (4 + 1 + 0 + 0.5) / 4)):
        terms = pointcloud.siren_sdf_losses(f_surface, g_surface, normals, f_space, g_space, 50.0, eikonal)
        assert float(terms["surface"]) == pytest.approx(0.2, rel=1e-12)
        assert float(terms["normal"]) == pytest.approx(((1 - 0.8) + (1 - 0.0)) / 2, rel=1e-12)
        assert float(terms["eikonal"]) == pytest.approx(expected, rel=1e-12), eikonal
        assert float(terms["offsurface"]) == pytest.approx((math.exp(-0.5) + math.exp(-1.0)) / 2, rel=1e-12)
    literal, parsed = "squared", "".join(["squ", "ared"])  # equal strings, not the same object
    assert parsed == literal and parsed is not literal
    terms = pointcloud.siren_sdf_losses(f_surface, g_surface, normals, f_space, g_space, 50.0, parsed)
    assert float(terms["eikonal"]) == pytest.approx((16 + 1 + 0 + 0.25) / 4, rel=1e-12)
    by_default = pointcloud.siren_sdf_losses(f_surface, g_surface, normals, f_space, g_space)
    assert float(by_default["eikonal"]) == pytest.approx((16 + 1 + 0 + 0.25) / 4, rel=1e-12)  # squared
    assert float(by_default["offsurface"]) == pytest.approx((math.exp(-1.0) + math.exp(-2.0)) / 2, rel=1e-12)
    for unknown in ("L1", "Squared", ""):  # a library call is not validated by a config: no silent "abs"
        with pytest.raises(ValueError, match=rf"^eikonal={unknown!r}: use 'squared' or 'abs'$"):
            pointcloud.siren_sdf_losses(f_surface, g_surface, normals, f_space, g_space, 50.0, unknown)


def test_the_loss_is_the_weighted_sum_of_the_four_terms(blob_points, tiny_grid):
    """Each step's loss equals w_surface * surface + w_normal * normal + w_eikonal * eikonal + w_offsurface
    * offsurface of the unweighted terms it reports (distinct weights, so no term can stand in for another)."""
    w = dict(w_surface=7.0, w_normal=3.0, w_eikonal=5.0, w_offsurface=11.0)
    trainer = tiny(tiny_grid, steps=2, output_bias=0.2, offsurface_falloff=5.0, **w).setup(blob_points)  # no term ~0
    trainer.fit()
    h = trainer.history
    for i in range(2):
        expected = sum(w[f"w_{t}"] * h[t][i] for t in ("surface", "normal", "eikonal", "offsurface"))
        assert h["loss"][i] == pytest.approx(expected, rel=1e-6)
    assert min(h[t][0] for t in ("surface", "normal", "eikonal", "offsurface")) > 1e-3  # every term counts


@pytest.mark.parametrize("steps", [1, 2, 5])
def test_the_learning_rate_decays_exponentially_to_exactly_lr_times_the_final_ratio(steps, blob_points, tiny_grid):
    """Step k (0-based) runs at ``lr * ratio ** (k / (steps - 1))``: the first at lr, the last at lr *
    ratio (one step: at lr)."""
    trainer = tiny(tiny_grid, steps=steps, lr=1e-2, lr_final_ratio=0.1).setup(blob_points)
    lrs = []
    trainer.optimizer.register_step_pre_hook(lambda opt, args, kwargs: lrs.append(opt.param_groups[0]["lr"]))
    trainer.fit()
    assert lrs == pytest.approx([1e-2 * 0.1 ** (k / max(steps - 1, 1)) for k in range(steps)], rel=1e-12)
    assert lrs[-1] == pytest.approx(1e-3 if steps > 1 else 1e-2, rel=1e-12)  # one step: at lr


def grads_at_the_optimizer_step(grid, points, grad_clip):
    trainer = tiny(grid, steps=1, grad_clip=grad_clip).setup(points)
    seen = []
    trainer.optimizer.register_step_pre_hook(
        lambda opt, args, kwargs: seen.append([p.grad.detach().clone() for p in trainer.field.parameters()]))
    trainer.step()
    return seen[0]


def test_gradient_clipping_scales_the_field_gradient_to_grad_clip_and_0_turns_it_off(blob_points, tiny_grid):
    """``--grad-clip 0`` leaves the gradient as backward made it (the same as a bound far above it); a
    positive bound below its norm scales it to that norm (torch's clip_grad_norm_: by
    ``bound / (norm + 1e-6)``)."""
    off = grads_at_the_optimizer_step(tiny_grid, blob_points, 0.0)
    far = grads_at_the_optimizer_step(tiny_grid, blob_points, 1e12)
    clipped = grads_at_the_optimizer_step(tiny_grid, blob_points, 0.01)
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in off]))
    assert norm > 1.0  # the weights (3e3 ...) make it large
    for a, b, c in zip(off, far, clipped):
        assert torch.equal(a, b)
        torch.testing.assert_close(c, a * (0.01 / (norm + 1e-6)), rtol=1e-5, atol=1e-12)


def test_the_learned_alpha_grid_is_left_alone_once_sp_has_ended(blob_points, tiny_grid):
    """After the schedule's end SP no longer reads the alpha grid, so it gets no gradient and Adam must not
    move it (``zero_grad(set_to_none=True)``: a parameter without a gradient is skipped; zeroed
    gradients would let Adam's momentum drift it)."""
    sp = SPConfig(alpha0=0.05, schedule="step", end=0.5, alpha_grid=True, alpha_grid_resolution=4)
    trainer = tiny(tiny_grid, steps=4, sp=sp).setup(blob_points)
    assert_alpha_grid_frozen_once_sp_ends(trainer)


def test_the_output_bias_applies_without_geometric_init_and_the_sphere_keeps_its_own(blob_points, tiny_grid):
    """``output_bias`` sets the MLP's last bias; with geometric init it is ignored (the sphere's
    ``-init_radius``); None keeps PyTorch's default (uniform in +-1/sqrt(width))."""
    def last_bias(**kw):
        return tiny(tiny_grid, **kw).setup(blob_points).field.mlp[-1].bias.detach()

    assert torch.equal(last_bias(output_bias=0.25), torch.tensor([0.25]))
    assert torch.equal(last_bias(geometric_init=True, init_radius=0.3), torch.tensor([-0.3]))
    assert torch.equal(last_bias(geometric_init=True, init_radius=0.3, output_bias=0.25), torch.tensor([-0.3]))
    default = float(last_bias(output_bias=None))
    assert 0 < abs(default) <= 1 / math.sqrt(16)


def test_a_diverged_fit_stops_in_one_line_naming_lr_and_grad_clip(blob_points, tiny_grid):
    """An absurd learning rate: the fit stops with the README's one line for a diverged ``sp-fit``, plus the
    point-cloud task's own hint."""
    trainer = tiny(tiny_grid, steps=3, lr=1e30).setup(blob_points)
    with pytest.raises(FloatingPointError) as stopped:
        trainer.fit()
    assert re.fullmatch(r"step [12]: the loss became (nan|inf); the fit diverged: lower --lr \(now 1e\+30, e\.g\. "
                        r"10x smaller\) or clip harder \(--grad-clip\)", str(stopped.value)), str(stopped.value)


def test_device_and_the_evaluation_options_are_keyword_only(blob_points, blob_mesh, tiny_grid):
    """``PointCloudSDFTrainer(config, data, *, device)`` and ``evaluate(gt_mesh, *, resolution, ...)``: a
    positional third argument is refused, not read as the device or the grid resolution."""
    assert_keyword_only_options(pointcloud.PointCloudSDFTrainer, tiny(tiny_grid), blob_points, blob_mesh)


def test_the_metrics_count_the_meshs_parts_and_zero_for_an_empty_mesh(blob_points, blob_mesh, tiny_grid):
    """``components`` in the metrics (metrics.json) is the number of the mesh's connected parts: 1 for the
    geometric init's sphere, 0 (not a negative count) for a field positive everywhere (output bias 5), which
    meshes to nothing."""
    sphere = tiny(tiny_grid, steps=1, geometric_init=True).setup(blob_points)
    mesh, metrics = sphere.evaluate(blob_mesh, resolution=12, refine=0, metric_points=100)
    assert len(mesh.faces) > 0
    assert metrics["components"] == 1
    positive = tiny(tiny_grid, steps=1, output_bias=5.0).setup(blob_points)
    mesh, metrics = positive.evaluate(blob_mesh, resolution=8, refine=0, metric_points=100)
    assert len(mesh.faces) == 0
    assert metrics["components"] == 0


def test_the_normal_and_eikonal_terms_train_the_field(blob_points, tiny_grid):
    """The gradient terms depend on the field's parameters through grad f (``create_graph=True``): with only
    w_normal, or only w_eikonal, non-zero, the field still gets a gradient."""
    for weights in (dict(w_normal=1.0), dict(w_eikonal=1.0)):
        w = dict(w_surface=0.0, w_normal=0.0, w_eikonal=0.0, w_offsurface=0.0)
        w.update(weights)
        trainer = tiny(tiny_grid, steps=1, grad_clip=0.0, **w).setup(blob_points)
        seen = []
        trainer.optimizer.register_step_pre_hook(
            lambda opt, args, kwargs: seen.append([p.grad.detach().clone() for p in trainer.field.parameters()]))
        trainer.step()
        assert max(float(g.abs().max()) for g in seen[0]) > 1e-6, weights


def test_include_input_feeds_the_coordinates_to_the_mlp_by_default_only_with_geometric_init(blob_points, tiny_grid):
    """The MLP's first layer reads the encoding's features, and 3 more inputs (the coordinates) when
    ``include_input`` is True, or when it is None (the default) with geometric init."""
    def inputs(**kw):
        return tiny(tiny_grid, **kw).setup(blob_points).field.mlp[0].in_features

    features = inputs()
    assert inputs(include_input=False) == features
    assert inputs(include_input=True) == features + 3
    assert inputs(geometric_init=True) == features + 3


def test_evaluate_reads_the_ground_truth_in_input_coordinates_unless_told_and_prints_nothing(blob_points, blob_mesh, tiny_grid, capfd):
    """``evaluate(gt)`` moves ``gt`` into the frame first (the same metrics as the moved mesh with
    ``gt_in_frame=True``, not those of the mesh as given); ``evaluate`` and ``fit`` show no progress unless
    asked."""
    trainer = tiny(tiny_grid, steps=2, geometric_init=True).setup(blob_points)
    trainer.fit()
    options = dict(resolution=12, refine=0, metric_points=200)
    _, default = trainer.evaluate(blob_mesh, **options)
    _, moved = trainer.evaluate(trainer.frame.mesh_to_frame(blob_mesh), gt_in_frame=True, **options)
    _, as_given = trainer.evaluate(blob_mesh, gt_in_frame=True, **options)
    assert default == moved
    assert default["chamfer"] != as_given["chamfer"]
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")


def test_components_counts_open_parts_too(blob_points, blob_mesh, tiny_grid):
    """A sphere larger than the box (the geometric init at radius 1.2) meshes to one open surface (cut by the
    box's walls): ``components`` is 1, not only the watertight parts."""
    trainer = tiny(tiny_grid, steps=1, geometric_init=True, init_radius=1.2).setup(blob_points)
    mesh, metrics = trainer.evaluate(blob_mesh, resolution=12, refine=0, metric_points=100)
    assert not mesh.is_watertight
    assert metrics["components"] == 1
