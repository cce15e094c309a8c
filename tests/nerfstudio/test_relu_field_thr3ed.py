"""The ReLU-field options that follow thr3ed_atom: cell grid, world-unit density, L1 + diffuse
loss, per-stage learning-rate restarts."""

from __future__ import annotations

import copy
import math
import subprocess

import pytest
import torch
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.field_components.field_heads import FieldHeadNames
from tests.helpers.ns_configs import run_recording, tiny_radiance_config

from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio.relu_field.field import DIFFUSE_RGB, ReLUField
from sp_plugins.nerfstudio.relu_field.lr import StagedStepDecaySchedulerConfig, staged_lr_factor
from sp_plugins.nerfstudio.relu_field.model import ReLUFieldModelConfig, stage_resolutions, voxel_size

BOX = SceneBox(aabb=torch.tensor([[-1.5] * 3, [1.5] * 3]))


def _samples(x, d=None):
    n = x.shape[0]
    d = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1) if d is None else d
    zeros = torch.zeros(n, 1, 1)
    return RaySamples(Frustums(origins=x[:, None], directions=d[:, None], starts=zeros, ends=zeros,
                               pixel_area=torch.ones(n, 1, 1)))


def test_cell_grid_stages_voxel_and_errors():
    assert stage_resolutions(64, 4, align_corners=False) == [8, 16, 32, 64]
    assert stage_resolutions(65, 4) == [9, 17, 33, 65]  # the vertex grid is unchanged
    assert voxel_size(BOX.aabb, 64, align_corners=False) == pytest.approx(3 / 64)
    assert voxel_size(BOX.aabb, 65) == pytest.approx(3 / 64)
    with pytest.raises(ValueError, match="multiple of 8"):
        ReLUFieldModelConfig(resolution=60, hierarchy_stages=4, align_corners=False)


def test_cell_grid_is_cell_centred_and_zero_outside():
    field = ReLUField(BOX.aabb, 4, color_mode="rgb", align_corners=False)
    field.grid.data.fill_(1.0)
    x = torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [1.9, 0.0, 0.0], [1.125, 1.125, 1.125]])
    v = field.lookup(x)[:, 0]
    # up to the last cell centre: the value; on a face: halfway to the zero outside; half a cell beyond: zero
    assert v.tolist() == pytest.approx([1.0, 0.5, 0.0, 1.0], abs=1e-6)
    vertex = ReLUField(BOX.aabb, 4, color_mode="rgb")  # a vertex grid keeps its value up to the face
    vertex.grid.data.fill_(1.0)
    assert float(vertex.lookup(x[1:2])[0, 0]) == pytest.approx(1.0)


def test_cell_grid_upsampling_keeps_the_coarse_field_at_the_new_centres():
    torch.manual_seed(0)
    field = ReLUField(BOX.aabb, 4, color_mode="rgb", align_corners=False)
    # fine centres (8 cells of 3/8) that lie between the first and last coarse centres (+-1.125)
    centres = -1.5 + 3 / 8 * (torch.arange(8) + 0.5)
    inner = centres[(centres.abs() <= 1.125)]
    x = torch.cartesian_prod(inner, inner, inner)
    before = field.lookup(x)
    coarse = copy.deepcopy(field)
    field.upsample_to(8)
    assert field.grid.shape[-3:] == (8, 8, 8)
    assert torch.allclose(field.lookup(x), before, atol=1e-5)
    # between centres the resampled field is smoother than the coarse one, not identical
    y = torch.rand(2000, 3) * 2.0 - 1.0
    assert not torch.allclose(field.lookup(y), coarse.lookup(y), atol=1e-3)


@pytest.mark.parametrize("units, resolution, expected", [("world", 64, 100 / 3), ("world", 16, 100 / 3),
                                                          ("voxel", 64, 64 / 3)])
def test_density_units(units, resolution, expected):
    config = ReLUFieldModelConfig(resolution=resolution, align_corners=False, hierarchy_stages=1, color_mode="rgb",
                                  density_units=units, density_scale=100 / 3 if units == "world" else 1.0)
    model = config.setup(scene_box=BOX, num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
    assert model.field.density_scale == pytest.approx(expected)
    model.field.grid.data[:, 0] = 0.5
    density, _ = model.field.get_density(_samples(torch.zeros(3, 3)))
    assert torch.allclose(density, torch.full_like(density, 0.5 * expected))


def _model(**kw):
    config = ReLUFieldModelConfig(resolution=8, align_corners=False, num_samples=8, **kw)
    return config.setup(scene_box=BOX, num_train_data=4, metadata={}, device="cpu", grad_scaler=None)


def test_l1_loss_and_the_diffuse_loss_on_the_degree_zero_render():
    torch.manual_seed(0)
    pred, gt = torch.rand(16, 3), torch.rand(16, 3)
    ones = torch.ones(16, 1)
    l1 = _model(loss="l1", color_mode="rgb").get_loss_dict({"rgb": pred, "accumulation": ones}, {"image": gt})
    assert set(l1) == {"rgb_loss"} and float(l1["rgb_loss"]) == pytest.approx(float((pred - gt).abs().mean()))
    model = _model(loss="l1", color_mode="sh", sh_degree=2, diffuse_loss_weight=0.5)
    model.train()
    diffuse = torch.rand(16, 3)
    losses = model.get_loss_dict({"rgb": pred, DIFFUSE_RGB: diffuse, "accumulation": ones}, {"image": gt})
    assert float(losses["diffuse_rgb_loss"]) == pytest.approx(0.5 * float((diffuse - gt).abs().mean()))


def test_diffuse_colour_is_the_degree_zero_term_and_trains_only_it():
    torch.manual_seed(0)
    field = ReLUField(BOX.aabb, 4, color_mode="sh", sh_degree=2, align_corners=False, diffuse_output=True)
    samples = _samples(torch.rand(64, 3) * 2 - 1)
    out = field(samples)
    out[DIFFUSE_RGB].sum().backward()
    grad = field.grid.grad.abs().flatten(2).sum(-1)[0]  # per channel: density, then 3 colours x 9 coefficients
    dc = [1 + 9 * c for c in range(3)]
    assert (grad[dc] > 0).all()
    assert grad[[i for i in range(grad.numel()) if i not in dc]].sum() == 0
    with torch.no_grad():  # without the higher-order terms the full colour is the diffuse one
        for c in range(3):
            field.grid[:, 2 + 9 * c : 10 + 9 * c] = 0.0
    out = field(samples)
    assert torch.allclose(out[DIFFUSE_RGB], out[FieldHeadNames.RGB])
    with pytest.raises(ValueError, match="color_mode 'sh'"):
        ReLUField(BOX.aabb, 4, color_mode="rgb", diffuse_output=True)


def test_staged_factor_hits_the_original_schedule():
    f = dict(total_steps=28000, stages=4, decay_every=3 / 28, first_decay=None, gamma=0.1, stage_gamma=0.9)
    got = [staged_lr_factor(s, **f) for s in (0, 2999, 3000, 5999, 6000, 6999, 7000, 10000, 27999)]
    want = [1, 1, 0.1, 0.1, 0.01, 0.01, 0.9, 0.09, 0.9**3 * 0.01]
    assert got == pytest.approx(want)
    flat_sp = dict(f, stages=1, first_decay=12 / 28)  # the paper's SP run: decay from step 12000
    got = [staged_lr_factor(s, **flat_sp) for s in (0, 11999, 12000, 14999, 15000)]
    assert got == pytest.approx([1, 1, 0.1, 0.1, 0.01])


def test_staged_schedule_restarts_at_the_trainers_upsampling(tiny_scene, tmp_path):
    config = tiny_radiance_config("relu-field", tiny_scene, tmp_path, steps=8)
    config.optimizers["fields"]["scheduler"] = StagedStepDecaySchedulerConfig(max_steps=8, stages=4, decay_every=1 / 8,
                                                                              stage_gamma=0.5)
    seen = []
    original_setup = config.setup

    def setup(**kw):
        trainer = original_setup(**kw)
        original = trainer.setup

        def trainer_setup(*a, **k):
            original(*a, **k)
            optimizer = trainer.optimizers.optimizers["fields"]

            def record(step):
                seen.append((optimizer.param_groups[0]["lr"], trainer.pipeline.model.field.resolution))

            trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], record))

        trainer.setup = trainer_setup
        return trainer

    config.setup = setup  # type: ignore[method-assign]
    _, record = run_recording(config)
    assert all(math.isfinite(loss) for loss, _, _ in record)
    # recorded after each step's scheduler update: the lr of the next step
    lrs = [lr / 0.03 for lr, _ in seen]
    assert lrs[:7] == pytest.approx([0.1, 0.5, 0.05, 0.25, 0.025, 0.125, 0.0125])
    assert [res for _, res in seen] == [3, 3, 5, 5, 9, 9, 17, 17]


def test_a_schedule_with_other_stages_than_the_model_is_refused(tiny_scene, tmp_path):
    config = tiny_radiance_config("relu-field", tiny_scene, tmp_path, steps=8)
    config.optimizers["fields"]["scheduler"] = StagedStepDecaySchedulerConfig(max_steps=8, stages=1)
    with pytest.raises(InputError, match="hierarchy-stages 4"):
        run_recording(config)


def test_thr3ed_flags_train_through_ns_train_and_a_misfit_is_one_line(tiny_scene, ns_server, tmp_path):
    """The run forked from the session's fork server; the misfit through the real ``ns-train`` script."""
    from tests.helpers.errors import refused
    from tests.helpers.ns_commands import ENV, RUN_FLAGS, command, ns_train

    data = ["blender-data", "--data", str(tiny_scene / "blender")]
    flags = ["--pipeline.model.resolution", "16", "--pipeline.model.align-corners", "False",
             "--pipeline.model.num-samples", "8", "--pipeline.model.density-units", "world",
             "--pipeline.model.density-scale", "33.3", "--pipeline.model.loss", "l1",
             "--pipeline.model.color-mode", "sh", "--pipeline.model.sh-degree", "2",
             "--pipeline.model.diffuse-loss-weight", "1.0"]
    config = ns_train("relu-field", tmp_path / "ok", data, *flags, steps=4, server=ns_server)
    text = config.read_text()
    assert "align_corners: false" in text and "loss: l1" in text and "diffuse_loss_weight: 1.0" in text
    state = torch.load(next(config.parent.glob("nerfstudio_models/*.ckpt")), map_location="cpu", weights_only=False)
    assert state["pipeline"]["_model.field.grid"].shape[1:] == (28, 16, 16, 16)  # 4 stages of 2 -> 16 cells

    bad = [command("ns-train"), "relu-field-flat", *RUN_FLAGS, "--output-dir", str(tmp_path / "bad"),
           "--pipeline.model.diffuse-loss-weight", "1.0", "--pipeline.model.color-mode", "rgb", *data]
    proc = subprocess.run(bad, capture_output=True, text=True, timeout=600, env=ENV)
    last = refused(proc, "ns-train", others=True)
    assert last.startswith("ns-train: error: --pipeline.model.diffuse-loss-weight 1 needs --pipeline.model.color-mode sh"), last
