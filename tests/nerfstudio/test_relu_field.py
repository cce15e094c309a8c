"""ReLU-field methods through nerfstudio's registry, trainer and checkpoints; the hierarchy."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from tests.helpers.ns_configs import run_recording, tiny_radiance_config

from sp_plugins.core import AlphaSchedule
from sp_plugins.nerfstudio.relu_field.field import ReLUField, upsample_grid
from sp_plugins.nerfstudio.relu_field.model import stage_at, stage_resolutions

RELU_METHODS = ("relu-field", "relu-field-flat", "sp-relu-field")
BOX = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


def tiny_relu_config(name, scene, out, *, steps=4, rays=64, **sp):
    return tiny_radiance_config(name, scene, out, steps=steps, rays=rays, **sp)


def run(config, stop_after=None):
    trainer, record = run_recording(config, stop_after)
    return trainer, [(loss, metrics) for loss, _, metrics in record]


def test_registry_lists_the_relu_field_methods():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    for name in RELU_METHODS:
        assert name in methods and methods[name].method_name == name and len(descriptions[name]) > 20
    stages = {name: methods[name].pipeline.model.hierarchy_stages for name in RELU_METHODS}
    assert stages == {"relu-field": 4, "relu-field-flat": 1, "sp-relu-field": 1}
    assert [methods[n].pipeline.model.sp.enabled for n in RELU_METHODS] == [False, False, True]
    config = methods["sp-relu-field"]
    sp = config.pipeline.model.sp
    # the paper's settings: alpha0 0.003 to 0 by step 8000 of 28000, kept as a ratio for shorter runs
    assert config.max_num_iterations == 28000 and sp.alpha0 == pytest.approx(0.003)
    assert round(sp.end * config.max_num_iterations) == 8000


def test_stage_resolutions_and_boundaries():
    assert stage_resolutions(129, 4) == [17, 33, 65, 129]
    assert stage_resolutions(65, 1) == [65]
    assert [stage_at(s, 100, 4) for s in (0, 24, 25, 50, 74, 75, 99, 150)] == [0, 0, 1, 2, 2, 3, 3, 3]
    with pytest.raises(ValueError, match="too coarse"):
        stage_resolutions(5, 4)


def test_upsampling_reproduces_the_coarse_field_exactly():
    torch.manual_seed(0)
    field = ReLUField(BOX.aabb, 5, color_mode="rgb")
    x = torch.rand(500, 3) * 2 - 1
    before = field.lookup(x)
    field.upsample_to(9)
    assert field.grid.shape[-3:] == (9, 9, 9)
    assert torch.allclose(field.lookup(x), before, atol=1e-5)
    # and the ReLU after interpolation makes a surface sharper than one voxel possible
    field.grid.data[:, 0] = -1.0
    field.grid.data[:, 0, :, :, 5:] = 1.0  # vertices at x >= 0.25 (spacing 0.25): the surface is x = 0.125
    d = torch.relu(field.lookup(torch.tensor([[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.13, 0.0, 0.0]]))[:, 0])
    assert d[0] == 0 and d[1] == 0 and 0 < d[2] < 0.1


@pytest.mark.parametrize("name", RELU_METHODS)
def test_method_trains_a_few_iterations(name, tiny_scene, tmp_path):
    trainer, record = run(tiny_relu_config(name, tiny_scene, tmp_path, steps=4))
    assert len(record) == 4 and all(math.isfinite(loss) for loss, _ in record)
    assert (record[0][1]["sp_alpha"] > 0) == name.startswith("sp-")
    model = trainer.pipeline.model
    assert int(model.sp.step) == 3 and int(model.sp.total_steps) == 4
    state = torch.load(sorted(trainer.checkpoint_dir.glob("*.ckpt"))[-1], map_location="cpu", weights_only=False)
    assert state["pipeline"]["_model.field.grid"].shape[-1] == 17
    assert not any("lpips" in key for key in state["pipeline"])


def test_hierarchy_changes_resolution_each_stage_and_trains_the_new_grid(tiny_scene, tmp_path):
    trainer, record = run(tiny_relu_config("relu-field", tiny_scene, tmp_path, steps=8))
    assert [m["grid_resolution"] for _, m in record] == [3, 3, 5, 5, 9, 9, 17, 17]
    model, optimizers = trainer.pipeline.model, trainer.optimizers
    grid = model.field.grid
    # the optimizer holds the current grid (and nothing stale), whose moments restarted at the last stage
    held = optimizers.optimizers["fields"].param_groups[0]["params"]
    assert len(held) == 1 and held[0] is grid and optimizers.parameters["fields"][0] is grid
    assert int(optimizers.optimizers["fields"].state[grid]["step"]) == 2
    assert grid.grad is not None and grid.grad.shape == grid.shape


def test_short_flat_training_lowers_the_loss(tiny_scene, tmp_path):
    _, record = run(tiny_relu_config("relu-field-flat", tiny_scene, tmp_path, steps=40, rays=256))
    first = sum(loss for loss, _ in record[:5]) / 5
    last = sum(loss for loss, _ in record[-5:]) / 5
    assert last < 0.6 * first, (first, last)


def test_training_queries_are_perturbed_and_eval_queries_are_not(tiny_scene, tmp_path):
    config = tiny_relu_config("sp-relu-field", tiny_scene, tmp_path, steps=100, end=0.5)
    model = config.pipeline.model.setup(scene_box=BOX, num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
    model.sp.set_step(0, 100)
    x = torch.rand(2, 32, 3) * 1.6 - 0.8
    from nerfstudio.cameras.rays import Frustums, RaySamples

    d = torch.nn.functional.normalize(torch.randn(2, 32, 3), dim=-1)
    samples = RaySamples(Frustums(origins=x, directions=d, starts=torch.zeros(2, 32, 1), ends=torch.zeros(2, 32, 1),
                                  pixel_area=torch.ones(2, 32, 1)))
    model.train()
    a, b = model.field(samples), model.field(samples)
    for key in a:
        assert not torch.allclose(a[key], b[key]), key
    model.eval()
    c, e = model.field(samples), model.field(samples)
    for key in c:
        assert torch.equal(c[key], e[key]), key
    model.sp.set_step(50, 100)  # the schedule has reached 0: training sees the plain field
    model.train()
    f = model.field(samples)
    for key in c:
        assert torch.allclose(f[key], c[key]), key


def test_checkpoint_of_a_later_stage_loads_and_resumes(tiny_scene, tmp_path):
    config = tiny_relu_config("relu-field", tiny_scene, tmp_path / "first", steps=8)
    config.pipeline.model.sp.enabled = True  # exercise SP state alongside the hierarchy
    first, _ = run(config, stop_after=4)  # stops in stage 2 (9^3)
    assert first.pipeline.model.field.resolution == 9
    ckpt = sorted(config.get_checkpoint_dir().glob("*.ckpt"))[-1]
    loaded = torch.load(ckpt, map_location="cpu", weights_only=False)

    # as ns-eval / ns-export load it: a fresh pipeline starts at 3^3 and takes the 9^3 grid
    fresh_config = tiny_relu_config("relu-field", tiny_scene, tmp_path / "fresh", steps=8)
    fresh_config.pipeline.model.sp.enabled = True
    fresh = fresh_config.pipeline.setup(device="cpu", test_mode="val")
    assert fresh.model.field.resolution == 3
    fresh.load_pipeline(loaded["pipeline"], loaded["step"])
    assert torch.equal(fresh.model.field.grid, first.pipeline.model.field.grid)
    assert (int(fresh.model.sp.step), int(fresh.model.sp.total_steps)) == (4, 8)

    # resume through the trainer: same stage, SP schedule continues, then the last upsampling happens
    resumed_config = tiny_relu_config("relu-field", tiny_scene, tmp_path / "resumed", steps=8)
    resumed_config.pipeline.model.sp.enabled = True
    resumed_config.load_dir = config.get_checkpoint_dir()
    resumed_config.max_num_iterations = 8
    second = resumed_config.setup(local_rank=0, world_size=1)
    second.setup()
    start = loaded["step"] + 1
    assert second._start_step == start and int(second.pipeline.model.sp.step) == start
    assert second.pipeline.model.sp.alpha == pytest.approx(AlphaSchedule("exponential", 0.05, end_step=7)(start))
    assert second.pipeline.model.field.resolution == 9
    for callback in second.callbacks:
        callback.run_callback_at_location(start, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    assert second.pipeline.model.field.resolution == 17
    assert second.optimizers.optimizers["fields"].param_groups[0]["params"][0] is second.pipeline.model.field.grid


def test_sp_and_grid_flags_parse_through_ns_train_cli(tiny_scene):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    args = ["sp-relu-field", "--pipeline.model.sp.alpha0", "0.02", "--pipeline.model.resolution", "65",
            "--pipeline.model.color-mode", "rgb", "--pipeline.datamanager.train-views", "4",
            "blender-data", "--data", str(tiny_scene / "blender")]
    config = tyro.cli(AnnotatedBaseConfigUnion, args=args)
    model = config.pipeline.model
    assert (model.sp.alpha0, model.resolution, model.color_mode) == (0.02, 65, "rgb")
    assert config.pipeline.datamanager.train_views == 4


def test_bad_settings_are_clear_errors():
    from sp_plugins.nerfstudio.relu_field.model import ReLUFieldModelConfig

    with pytest.raises(ValueError, match="sh_degree"):
        ReLUFieldModelConfig(sh_degree=5)
    with pytest.raises(ValueError, match="color_mode"):
        ReLUFieldModelConfig(color_mode="hsv")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="too coarse"):
        ReLUFieldModelConfig(resolution=5, hierarchy_stages=4)


def test_upsample_grid_doubles_cells():
    g = torch.arange(8.0).view(1, 1, 2, 2, 2)
    up = upsample_grid(g, 3)
    assert up.shape == (1, 1, 3, 3, 3) and up[0, 0, 1, 1, 1] == pytest.approx(g.mean())


def test_ns_eval_loads_the_final_grid_of_a_hierarchical_run(tiny_scene, tmp_path):
    import json

    from nerfstudio.scripts.eval import ComputePSNR

    config = tiny_relu_config("relu-field", tiny_scene, tmp_path, steps=8)
    trainer, _ = run(config)
    assert trainer.pipeline.model.field.resolution == 17
    out = tmp_path / "eval.json"
    ComputePSNR(load_config=config.get_base_dir() / "config.yml", output_path=out).main()
    results = json.loads(out.read_text())["results"]
    assert math.isfinite(results["psnr"]) and "ssim" in results
    assert not any(k.endswith("lpips") and not math.isfinite(v) for k, v in results.items())


def test_random_background_trains_on_rgba_and_refuses_composited_images(tiny_scene, tmp_path):
    config = tiny_relu_config("relu-field-flat", tiny_scene, tmp_path / "rgb", steps=2)
    config.pipeline.model.background_color = "random"
    with pytest.raises(ValueError, match="alpha-color None"):
        run(config)
    config = tiny_relu_config("relu-field-flat", tiny_scene, tmp_path / "rgba", steps=2)
    config.pipeline.model.background_color = "random"
    config.pipeline.datamanager.dataparser.alpha_color = None
    _, record = run(config)
    assert all(math.isfinite(loss) for loss, _ in record)


def _capture_lookups(field):
    """Record the positions the grid is read at (after SP)."""
    seen = []
    plain = field.lookup

    def lookup(x):
        seen.append(x.detach().clone())
        return plain(x)

    field.lookup = lookup
    return seen


def _samples_at(x):
    from nerfstudio.cameras.rays import Frustums, RaySamples

    n = x.shape[0]
    zeros = torch.zeros(n, 1, 1)
    return RaySamples(Frustums(origins=x[:, None], directions=torch.nn.functional.normalize(torch.randn(n, 1, 3), dim=-1),
                               starts=zeros, ends=zeros, pixel_area=torch.ones(n, 1, 1)))


def test_sp_offsets_in_world_units_are_alpha_voxels_reflected_and_training_only(tiny_scene, tmp_path):
    from sp_plugins.nerfstudio.relu_field.model import voxel_size

    box = SceneBox(aabb=torch.tensor([[-1.5] * 3, [1.5] * 3]))  # the bench's box and grid: 129^3, voxel 3/128
    voxels = 2.0
    alpha = voxels * voxel_size(box.aabb, 129)
    assert alpha == pytest.approx(2 * 3 / 128)
    config = tiny_relu_config("sp-relu-field", tiny_scene, tmp_path, steps=100, alpha0=alpha, end=0.5, schedule="constant")
    config.pipeline.model.resolution, config.pipeline.model.color_mode = 129, "rgb"
    model = config.pipeline.model.setup(scene_box=box, num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
    assert model.field.density_scale == pytest.approx(1.0 / voxel_size(box.aabb, 129))  # the same voxel
    model.sp.set_step(0, 100)
    seen = _capture_lookups(model.field)
    torch.manual_seed(0)
    inner = torch.rand(20000, 3) * 2.0 - 1.0  # at least 10 alphas from every wall
    wall = torch.rand(20000, 3) * 2 * alpha + (1.5 - 2 * alpha)  # within 2 alphas of the +x/+y/+z walls
    model.train()  # the model calls its field's forward: the seam moves the samples there
    model.field.forward(_samples_at(inner))
    model.field.forward(_samples_at(wall))
    offsets = seen[0] - inner
    assert offsets.mean(0).abs().max() < 0.05 * alpha
    assert torch.allclose(offsets.std(0), torch.full((3,), alpha), rtol=0.03)
    assert (seen[1].abs() <= 1.5).all()  # reflected back into the box, never read in the zeroed outside
    assert ((seen[1] - wall).abs() > 2 * alpha).any()  # (there was something to reflect)
    assert ((seen[1] - wall).std(0) < alpha).all()  # a reflected kernel is narrower near the wall
    model.eval()
    model.field.forward(_samples_at(inner))
    assert torch.equal(seen[2], inner)


def test_schedule_callback_sets_the_scheduled_alpha_at_every_training_step(tiny_scene, tmp_path):
    _, record = run(tiny_relu_config("sp-relu-field", tiny_scene, tmp_path, steps=6, alpha0=0.05, end=4))
    schedule = AlphaSchedule("exponential", 0.05, end_step=4)
    assert [m["sp_alpha"] for _, m in record] == pytest.approx([schedule(step) for step in range(6)])
    assert record[0][1]["sp_alpha"] == pytest.approx(0.05) and record[-1][1]["sp_alpha"] == 0.0


def test_ns_export_pointcloud_from_a_relu_field_checkpoint(tiny_scene, tmp_path):
    pytest.importorskip("open3d", exc_type=ImportError)  # also skips when libusb-1.0 is missing (see run.sh)
    from nerfstudio.scripts.exporter import ExportPointCloud

    config = tiny_relu_config("sp-relu-field", tiny_scene, tmp_path, steps=3)
    run(config)
    out = tmp_path / "export"
    ExportPointCloud(load_config=config.get_base_dir() / "config.yml", output_dir=out, num_points=200,
                     normal_method="open3d", remove_outliers=False, num_rays_per_batch=256).main()
    import trimesh

    cloud = trimesh.load(out / "point_cloud.ply")
    assert len(cloud.vertices) > 0 and (abs(cloud.vertices) <= 1.5 + 1e-4).all()  # depths inside the scene box
