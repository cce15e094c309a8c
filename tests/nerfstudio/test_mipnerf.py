"""sp-mipnerf: SP, through the one seam, on the mean of each conical frustum's Gaussian."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.vanilla_nerf_field import NeRFField
from tests.helpers.ns_configs import run_recording, tiny_radiance_config

from sp_plugins.core import AlphaSchedule, SPConfig, StochasticPreconditioner
from sp_plugins.nerfstudio.seam import SeamField, attach_seam

BOX = SceneBox(aabb=torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]))


def frustum_samples(n_rays=4, n=8):
    torch.manual_seed(1)
    o = torch.tensor([0.0, 0.0, 4.0]).expand(n_rays, n, 3)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.1 * torch.randn(n_rays, 1, 3), dim=-1).expand(n_rays, n, 3)
    t = torch.linspace(2.5, 5.5, n + 1)
    return RaySamples(Frustums(origins=o, directions=d, starts=t[:-1].expand(n_rays, n)[..., None],
                               ends=t[1:].expand(n_rays, n)[..., None], pixel_area=torch.full((n_rays, n, 1), 1e-3)))


def test_registry_and_paper_settings():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    config = methods["sp-mipnerf"]
    sp = config.pipeline.model.sp
    assert (sp.alpha0, sp.schedule, sp.enabled) == (pytest.approx(0.04), "exponential", True)
    # the paper's step 2500, as a third of the preset's length so that shortened runs keep the ratio
    assert round(sp.end * methods["sp-mipnerf"].max_num_iterations) == 2500
    assert config.pipeline.model.loss_coefficients == {"rgb_loss_coarse": 0.1, "rgb_loss_fine": 1.0}
    assert "train-views" in descriptions["sp-mipnerf"]


def test_the_offset_moves_the_gaussian_mean_and_keeps_the_covariance():
    from nerfstudio.field_components.encodings import NeRFEncoding

    torch.manual_seed(0)
    enc = NeRFEncoding(in_dim=3, num_frequencies=6, min_freq_exp=0.0, max_freq_exp=6.0, include_input=True)
    direnc = NeRFEncoding(in_dim=3, num_frequencies=2, min_freq_exp=0.0, max_freq_exp=2.0, include_input=True)
    holder = torch.nn.Module()
    holder.field = NeRFField(position_encoding=enc, direction_encoding=direnc, base_mlp_num_layers=2, base_mlp_layer_width=32,
                             use_integrated_encoding=True)
    field = holder.field
    plain_density = field.forward(frustum_samples())[FieldHeadNames.DENSITY]

    def sp_with_seed(alpha):
        sp = StochasticPreconditioner(SPConfig(alpha0=alpha, schedule="constant", boundary="none", seed=7))
        sp.set_step(0, 10)
        return sp.train()

    attach_seam(holder, sp_with_seed(0.05))
    field = holder.field
    density = field.forward(frustum_samples())[FieldHeadNames.DENSITY]
    # the same computation by hand: one N(0, alpha^2) draw added to each Gaussian mean, same covariance
    blobs = frustum_samples().frustums.get_gaussian_blob()
    mean = sp_with_seed(0.05)(blobs.mean.reshape(-1, 3)).view(blobs.mean.shape)
    expected = field.field_output_density(field.mlp_base(enc(mean, covs=blobs.cov)))
    assert torch.allclose(density, expected, atol=1e-6)
    assert not torch.allclose(density, plain_density)
    field.eval()
    assert torch.equal(field.forward(frustum_samples())[FieldHeadNames.DENSITY], plain_density)


@pytest.mark.parametrize("enabled", [True, False])
def test_sp_mipnerf_trains_a_few_iterations(enabled, tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-mipnerf", tiny_scene, tmp_path, steps=3, enabled=enabled)
    trainer, record = run_recording(config)
    assert len(record) == 3
    for step, (loss, parts, metrics) in enumerate(record):
        assert math.isfinite(loss) and set(parts) == {"rgb_loss_coarse", "rgb_loss_fine"}
        assert (metrics["sp_alpha"] > 0) == (enabled and step < 2)  # end 1.0: the last step is plain
    model = trainer.pipeline.model
    assert isinstance(model.field, SeamField)
    # eval metrics without LPIPS weights: the NaN entry is dropped, the others are there
    model.eval()
    camera = trainer.pipeline.datamanager.eval_dataset.cameras[0:1]
    batch = trainer.pipeline.datamanager.eval_dataset[0]
    outputs = model.get_outputs_for_camera(camera)
    metrics, _ = model.get_image_metrics_and_images(outputs, batch)
    assert math.isfinite(metrics["psnr"]) and all(math.isfinite(v) for v in metrics.values())


def test_training_queries_are_perturbed_and_eval_queries_are_not(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-mipnerf", tiny_scene, tmp_path, steps=5000, alpha0=0.04, end=2500)
    model = config.pipeline.model.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)
    schedule = AlphaSchedule("exponential", 0.04, end_step=2500)
    for step in (0, 1000, 2499, 2500):
        model.sp.set_step(step, 5000)
        assert model.sp.alpha == pytest.approx(schedule(step))
    model.sp.set_step(100, 5000)
    rs = frustum_samples()
    model.train()
    a, b = model.field.forward(rs), model.field.forward(rs)
    assert not torch.allclose(a[FieldHeadNames.DENSITY], b[FieldHeadNames.DENSITY])
    model.eval()
    c, d = model.field.forward(rs), model.field.forward(rs)
    for key in c:
        assert torch.equal(c[key], d[key])


def test_schedule_that_ends_after_training_is_a_clear_error(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-mipnerf", tiny_scene, tmp_path, steps=100, end=2500)
    with pytest.raises(ValueError, match="after the end of training"):
        run_recording(config)


def test_checkpoint_round_trip_restores_sp_state(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-mipnerf", tiny_scene, tmp_path / "first", steps=10)
    first, _ = run_recording(config, stop_after=2)
    loaded = torch.load(sorted(config.get_checkpoint_dir().glob("*.ckpt"))[-1], map_location="cpu", weights_only=False)
    fresh = tiny_radiance_config("sp-mipnerf", tiny_scene, tmp_path / "fresh", steps=10).pipeline.setup(device="cpu", test_mode="val")
    fresh.load_pipeline(loaded["pipeline"], loaded["step"])
    assert (int(fresh.model.sp.step), int(fresh.model.sp.total_steps)) == (int(first.pipeline.model.sp.step), 10)
    assert isinstance(fresh.model.field, SeamField)
    for key, value in first.pipeline.model.field.state_dict().items():
        assert torch.equal(fresh.model.field.state_dict()[key], value), key


def test_ns_eval_runs_on_a_sparse_view_checkpoint(tiny_scene, tmp_path):
    import json

    from nerfstudio.scripts.eval import ComputePSNR
    from nerfstudio.utils.eval_utils import eval_setup

    config = tiny_radiance_config("sp-mipnerf", tiny_scene, tmp_path, steps=2)
    config.pipeline.datamanager.train_views = 3
    run_recording(config)
    out = tmp_path / "eval.json"
    ComputePSNR(load_config=config.get_base_dir() / "config.yml", output_path=out).main()
    results = json.loads(out.read_text())["results"]
    assert math.isfinite(results["psnr"]) and "fine_lpips" not in results
    # inference mode (ns-render, viewer) rebuilds the same 3-view model from the saved config
    _, pipeline, _, _ = eval_setup(config.get_base_dir() / "config.yml", test_mode="inference")
    assert pipeline.model.num_train_data == 3 and isinstance(pipeline.model.field, SeamField)
