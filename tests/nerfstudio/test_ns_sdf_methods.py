"""SDF methods through nerfstudio's own machinery: registry, CLI parsing, trainer, checkpoints."""

from __future__ import annotations

import math

import pytest
import torch
from tests.helpers.ns_configs import SDF_METHODS, tiny_sdf_config, run_recording

from nerfstudio.field_components.field_heads import FieldHeadNames
from sp_plugins.core import AlphaSchedule
from sp_plugins.nerfstudio.neus import NeuralangeloLiteModel, SPNeuSModel


def test_registry_lists_our_methods_with_descriptions():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    for name in SDF_METHODS:
        assert name in methods, f"{name} not discovered through the nerfstudio.method_configs entry points"
        assert methods[name].method_name == name
        assert len(descriptions[name]) > 20
    assert methods["sp-neus"].pipeline.model.sp.enabled
    assert not methods["neus-hashgrid"].pipeline.model.sp.enabled
    assert methods["neuralangelo-lite"].pipeline.model.coarse_to_fine
    assert not methods["sp-neuralangelo-lite"].pipeline.model.coarse_to_fine
    # the paper's settings
    assert methods["sp-neus-hashgrid"].pipeline.model.sp.alpha0 == pytest.approx(0.013)
    assert methods["sp-neuralangelo-lite"].pipeline.model.sp.alpha0 == pytest.approx(0.03)
    grid = methods["neus-hashgrid"].pipeline.model.sdf_field
    assert (grid.num_levels, grid.base_res, grid.max_res, grid.log2_hashmap_size, grid.features_per_level) == (16, 16, 2048, 19, 2)


def test_sp_flags_parse_through_ns_train_cli(tiny_scene):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    args = ["sp-neuralangelo-lite", "--pipeline.model.sp.alpha0", "0.05", "--pipeline.model.sp.alpha-grid", "True",
            "--pipeline.model.sp.end", "0.5", "sdfstudio-data", "--data", str(tiny_scene / "sdfstudio")]
    config = tyro.cli(AnnotatedBaseConfigUnion, args=args)
    sp = config.pipeline.model.sp
    assert (sp.alpha0, sp.alpha_grid, sp.end) == (0.05, True, 0.5)
    assert config.pipeline.datamanager.dataparser.data == tiny_scene / "sdfstudio"


@pytest.mark.parametrize(
    "name,layout",
    [("sp-neus", "sdfstudio"), ("neus-hashgrid", "blender"), ("sp-neus-hashgrid", "sdfstudio"),
     ("sp-neus-hashgrid", "blender"), ("neuralangelo-lite", "blender"), ("sp-neuralangelo-lite", "sdfstudio")],
)
def test_method_trains_a_few_iterations(name, layout, tiny_scene, tiny_config, tmp_path):
    config = tiny_config(name, tiny_scene, tmp_path, layout=layout, steps=3, alpha0=0.05, end=1.0)
    trainer, losses = run_recording(config)
    assert len(losses) == 3
    for loss, parts, _ in losses:
        assert math.isfinite(loss) and all(math.isfinite(v) for v in parts.values())
    assert {"rgb_loss", "eikonal_loss"} <= set(losses[0][1])
    model = trainer.pipeline.model
    if "neuralangelo" in name:
        assert "curvature_loss" in losses[-1][1]
    # SP was on exactly for the SP methods, and the trainer's step reached the preconditioner
    sp_alphas = [m["sp_alpha"] for _, _, m in losses]
    assert (sp_alphas[0] > 0) == name.startswith("sp-")
    assert int(model.sp.step) == 2 and int(model.sp.total_steps) == 3
    # a checkpoint was written, without LPIPS weights in it
    ckpt = sorted(config.get_checkpoint_dir().glob("*.ckpt"))
    assert ckpt, "no checkpoint written"
    state = torch.load(ckpt[-1], map_location="cpu", weights_only=False)["pipeline"]
    assert "_model.sp.step" in state and not any("lpips" in k for k in state)


def _ray_samples(model, pipeline, n_rays=16):
    """NeuS samples on a few training rays (with the sampler's own plain-field queries)."""
    bundle, _ = pipeline.datamanager.next_train(0)
    bundle = bundle[:n_rays]
    bundle = model.collider(bundle)
    with torch.no_grad():
        return model.sampler(bundle, sdf_fn=model.field.get_sdf)


@pytest.fixture(scope="module")
def sp_pipeline(tiny_scene, tmp_path_factory):
    """An sp-neus-hashgrid pipeline set up by the trainer (no iterations run)."""
    config = tiny_sdf_config("sp-neus-hashgrid", tiny_scene, tmp_path_factory.mktemp("run"), steps=100, alpha0=0.05, end=0.5, seed=3)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def test_training_queries_are_perturbed_and_eval_queries_are_not(sp_pipeline):
    model = sp_pipeline.pipeline.model
    model.sp.set_step(0, 100)
    assert model.sp.alpha == pytest.approx(0.05)
    samples = _ray_samples(model, sp_pipeline.pipeline)
    model.train()
    a = model.field(samples, return_alphas=True)
    b = model.field(samples, return_alphas=True)
    for key in a:
        assert not torch.allclose(a[key], b[key]), f"{key}: two training queries at alpha > 0 agree"
    model.eval()
    c = model.field(samples, return_alphas=True)
    d = model.field(samples, return_alphas=True)
    for key in c:
        assert torch.equal(c[key], d[key]), f"{key}: eval queries must be deterministic"
    # once the schedule reaches 0, training queries are the plain field too
    model.sp.set_step(60, 100)
    model.train()
    e = model.field(samples, return_alphas=True)
    for key in c:
        assert torch.allclose(e[key], c[key], atol=1e-6), key
    model.eval()


def _samples_at(x):
    """One sample per row of ``x`` ``[n, 3]``: a zero-length bin starting there."""
    from nerfstudio.cameras.rays import Frustums, RaySamples

    n = x.shape[0]
    zeros = torch.zeros(n, 1, 1)
    return RaySamples(Frustums(origins=x[:, None], directions=torch.nn.functional.normalize(torch.randn(n, 1, 3), dim=-1),
                               starts=zeros, ends=zeros, pixel_area=torch.ones(n, 1, 1)),
                      camera_indices=torch.zeros(n, 1, 1, dtype=torch.long))


def _moved_outputs(model, x):
    """``(q, outputs)``: what the SDF field computes while training, on the samples the seam hands it."""
    from sp_plugins.nerfstudio.seam import SeamFrustums

    seen = {}
    plain = model.field.get_outputs

    def get_outputs(ray_samples, *args, **kwargs):  # the host's forward calls this with the moved samples
        assert isinstance(ray_samples.frustums, SeamFrustums)
        seen["q"] = ray_samples.frustums.get_start_positions().reshape(-1, 3).detach()
        return plain(ray_samples, *args, **kwargs)

    model.field.get_outputs = get_outputs
    try:
        outputs = model.field.forward(_samples_at(x))
    finally:
        del model.field.get_outputs
    return seen["q"], outputs


def test_analytic_normals_are_the_gradient_at_the_perturbed_point(sp_pipeline):
    model = sp_pipeline.pipeline.model
    field = model.field
    model.sp.set_step(0, 100)
    model.train()
    x = torch.rand(64, 3) * 1.2 - 0.6
    q, outputs = _moved_outputs(model, x)
    assert (q - x).abs().max() > 1e-3  # really perturbed
    q_plain = q.clone().requires_grad_(True)
    expected = torch.autograd.grad(field.forward_geonetwork(q_plain)[:, 0].sum(), q_plain)[0]
    assert torch.allclose(outputs[FieldHeadNames.GRADIENT].reshape(-1, 3), expected, atol=1e-5)
    assert torch.allclose(outputs[FieldHeadNames.SDF].reshape(-1), field.forward_geonetwork(q)[:, 0], atol=1e-6)
    model.eval()


def test_schedule_callback_sets_the_scheduled_alpha(sp_pipeline):
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    model = sp_pipeline.pipeline.model
    total = sp_pipeline.config.max_num_iterations
    expected = AlphaSchedule("exponential", 0.05, end_step=round(0.5 * total))
    for step in (0, 7, 25, 49, 50, 80):
        for callback in sp_pipeline.callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        assert model.sp.alpha == pytest.approx(expected(step), abs=1e-12)
        assert int(model.sp.step) == step and int(model.sp.total_steps) == total
    assert model.sp.alpha == 0.0 and 0 < expected(25) < 0.05


def test_numerical_gradient_stencil_shares_one_offset(tiny_scene, tiny_config, tmp_path):
    config = tiny_config("sp-neuralangelo-lite", tiny_scene, tmp_path, steps=10, alpha0=0.05, end=1.0)
    model = config.pipeline.model.setup(
        scene_box=_box(), num_train_data=4, metadata={}, device="cpu", grad_scaler=None
    )
    field = model.field
    model.sp.set_step(0, 10)
    field.set_fd_step(1e-3)
    model.train()
    x = torch.rand(128, 3) - 0.5
    q, outputs = _moved_outputs(model, x)
    grad, lap = outputs[FieldHeadNames.GRADIENT].reshape(-1, 3), outputs.get("sdf_laplacian")
    assert (q - x).abs().mean() > 0.01
    q_plain = q.detach().clone().requires_grad_(True)
    autograd = torch.autograd.grad(field.forward_geonetwork(q_plain)[:, 0].sum(), q_plain)[0]
    # central differences around the perturbed centre match its analytic gradient; an offset
    # drawn per stencil point would be off by about alpha / step = 50x the gradient
    assert torch.allclose(grad, autograd, atol=2e-3 * autograd.abs().max().item() + 1e-4)
    assert lap is not None and torch.isfinite(lap).all()


def _box():
    from nerfstudio.data.scene_box import SceneBox

    return SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


def test_coarse_to_fine_progresses_and_sp_variant_starts_with_all_levels(tiny_scene, tiny_config, tmp_path):
    c2f = tiny_config("neuralangelo-lite", tiny_scene, tmp_path / "a", steps=100)
    c2f.pipeline.model.c2f_warmup, c2f.pipeline.model.c2f_end = 0.1, 0.7  # 6 levels beyond 2, every 10 steps from 10
    model: NeuralangeloLiteModel = c2f.pipeline.model.setup(scene_box=_box(), num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
    levels, steps_fd = [], []
    for step in (0, 19, 20, 45, 70, 99):
        model.coarse_to_fine_at(step, 100)
        levels.append(int(model.field.active_levels))
        steps_fd.append(float(model.field.fd_step))
    assert levels == [2, 2, 3, 5, 8, 8]
    assert all(a > b for a, b in zip(steps_fd[1:4], steps_fd[2:5]))  # the FD step shrinks with each level
    assert steps_fd[-1] == pytest.approx(1.0 / model.field.encoding.levels[7].resolution)  # Neuralangelo: 1/res
    # masked levels are really off: the encoding's fine features are zero
    model.coarse_to_fine_at(0, 100)
    feats = model.field.encoding(torch.rand(5, 3))
    assert torch.all(feats[:, 2 * 2 :] == 0) and feats[:, : 2 * 2].abs().sum() > 0

    sp = tiny_config("sp-neuralangelo-lite", tiny_scene, tmp_path / "b", steps=100)
    sp_model = sp.pipeline.model.setup(scene_box=_box(), num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
    sp_model.coarse_to_fine_at(0, 100)
    assert int(sp_model.field.active_levels) == 8
    assert float(sp_model.field.fd_step) == pytest.approx(1.0 / sp_model.field.encoding.levels[7].resolution)


@pytest.mark.parametrize("alpha_grid", [False, True])
def test_checkpoint_round_trip_and_resume_restore_sp_state(alpha_grid, tiny_scene, tiny_config, tmp_path):
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    name = "sp-neuralangelo-lite" if alpha_grid else "sp-neus-hashgrid"
    sp = dict(alpha0=0.05, end=1.0, alpha_grid=alpha_grid, alpha_grid_resolution=4, alpha_grid_lr=0.05)
    config = tiny_config(name, tiny_scene, tmp_path / "first", steps=20, **sp)
    if alpha_grid:
        config.pipeline.model.c2f_end = 0.1
    first = config.setup(local_rank=0, world_size=1)
    first.setup()

    def stop(step):
        first.stop_training = True

    first.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], stop, iters=(4,)))
    first.train()  # 5 of 20 iterations, then the trainer saves a checkpoint and stops
    sp1 = first.pipeline.model.sp
    assert int(sp1.step) == 4 and sp1.alpha > 0
    grid1 = sp1.alpha_grid.values().clone() if alpha_grid else None
    if alpha_grid:
        assert not torch.allclose(grid1, torch.full_like(grid1, 0.03), atol=1e-4), "the alpha grid did not learn"
    ckpt = sorted(config.get_checkpoint_dir().glob("*.ckpt"))[-1]
    loaded = torch.load(ckpt, map_location="cpu", weights_only=False)

    # round trip into a fresh pipeline, as ns-eval / ns-export load it
    fresh = tiny_config(name, tiny_scene, tmp_path / "fresh", steps=20, **sp).pipeline.setup(device="cpu", test_mode="val")
    assert int(fresh.model.sp.step) == 0
    fresh.load_pipeline(loaded["pipeline"], loaded["step"])
    sp2 = fresh.model.sp
    assert (int(sp2.step), int(sp2.total_steps)) == (4, 20)
    # end 1.0 of 20 steps: SP ends at step 19; an alpha grid replaces the scalar (its nominal init) until then
    expected = (lambda step: 0.03) if alpha_grid else AlphaSchedule("exponential", 0.05, end_step=19)
    assert sp2.alpha == pytest.approx(expected(4))
    if alpha_grid:
        assert torch.equal(sp2.alpha_grid.values(), grid1)
        assert int(fresh.model.field.active_levels) == int(first.pipeline.model.field.active_levels)

    # resume through the trainer: it continues the same schedule from the checkpoint's step
    resumed = tiny_config(name, tiny_scene, tmp_path / "resumed", steps=20, **sp)
    resumed.load_dir = config.get_checkpoint_dir()
    second = resumed.setup(local_rank=0, world_size=1)
    second.setup()
    sp3 = second.pipeline.model.sp
    assert second._start_step == loaded["step"] + 1 and int(sp3.step) == second._start_step
    assert sp3.alpha == pytest.approx(expected(second._start_step))
    if alpha_grid:
        assert torch.equal(sp3.alpha_grid.values(), grid1)
        assert second.optimizers.optimizers["sp_alpha_grid"].param_groups[0]["lr"] == pytest.approx(0.05)


def test_eval_metrics_skip_missing_lpips_and_export_callable_works(sp_pipeline, tmp_path, caplog):
    from sp_plugins.nerfstudio.components import lpips

    pipeline = sp_pipeline.pipeline
    model = pipeline.model
    assert isinstance(model, SPNeuSModel)
    model.eval()
    if lpips.lpips_available():
        pytest.skip("LPIPS weights are cached here: the skip path is not exercised")
    assert not getattr(model.lpips, "available", True)
    camera = pipeline.datamanager.eval_dataset.cameras[0:1]
    batch = pipeline.datamanager.eval_dataset[0]
    outputs = model.get_outputs_for_camera(camera)
    metrics, images = model.get_image_metrics_and_images(outputs, batch)
    assert "psnr" in metrics and "ssim" in metrics and "lpips" not in metrics
    assert math.isfinite(metrics["psnr"]) and images["img"].shape[-1] == 3
    # what ns-export marching-cubes evaluates: forward_geonetwork(x)[:, 0], deterministic in eval
    x = torch.rand(1000, 3) * 2 - 1
    with torch.no_grad():
        a = model.field.forward_geonetwork(x)[:, 0]
        b = model.field.forward_geonetwork(x)[:, 0]
    assert a.shape == (1000,) and torch.equal(a, b)


def test_sampler_queries_see_the_plain_field_unless_asked(sp_pipeline):
    model = sp_pipeline.pipeline.model
    field = model.field
    model.sp.set_step(0, 100)
    model.train()
    samples = _ray_samples(model, sp_pipeline.pipeline)
    with torch.no_grad():
        assert torch.equal(field.get_sdf(samples), field.get_sdf(samples))
        field.config.perturb_sampler_queries = True
        try:
            assert not torch.allclose(field.get_sdf(samples), field.get_sdf(samples))
        finally:
            field.config.perturb_sampler_queries = False
    model.eval()


def test_a_schedule_longer_than_training_names_the_flags(tiny_scene, tmp_path):
    config = tiny_sdf_config("sp-neus-hashgrid", tiny_scene, tmp_path, steps=20, alpha0=0.05, end=500)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    with pytest.raises(ValueError, match=r"--pipeline.model.sp.end 500 does not fit --max-num-iterations 20"):
        trainer.setup()


def test_background_mlp_size_is_configurable_and_defaults_to_the_hosts(tiny_scene, tiny_config, tmp_path):
    """``background_mlp_layers/width`` rebuild the NeRF++ background at that size; the default is nerfstudio's 8 x 256."""
    sizes = {}
    for layers, width in ((8, 256), (3, 32)):
        config = tiny_config("neus-hashgrid", tiny_scene, tmp_path)
        model_config = config.pipeline.model
        model_config.background_model = "mlp"
        model_config.background_mlp_layers, model_config.background_mlp_width = layers, width
        model = model_config.setup(scene_box=_box(), num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
        linears = [m for m in model.field_background.mlp_base.modules() if isinstance(m, torch.nn.Linear)]
        sizes[(layers, width)] = (len(linears), {m.out_features for m in linears})
        out = model.field_background(_bg_samples())
        assert out[FieldHeadNames.RGB].shape == (4, 5, 3)
    assert sizes[(8, 256)] == (8, {256})
    assert sizes[(3, 32)] == (3, {32})
    config = tiny_config("neus-hashgrid", tiny_scene, tmp_path)
    config.pipeline.model.background_model = "mlp"
    config.pipeline.model.background_mlp_layers = 0
    with pytest.raises(ValueError, match="background_mlp_layers"):
        config.pipeline.model.setup(scene_box=_box(), num_train_data=4, metadata={}, device="cpu", grad_scaler=None)


def _bg_samples():
    from nerfstudio.cameras.rays import Frustums, RaySamples

    shape = (4, 5)
    frustums = Frustums(origins=torch.zeros(*shape, 3), directions=torch.nn.functional.normalize(torch.randn(*shape, 3), dim=-1),
                        starts=torch.rand(*shape, 1) + 2, ends=torch.rand(*shape, 1) + 3, pixel_area=torch.ones(*shape, 1))
    return RaySamples(frustums=frustums)
