"""freenerf-lite: FreeNeRF's frequency mask opens on schedule, its occlusion term reads the first
samples of the coarse pass only, it trains (also as ``sp-train freenerf-lite``) and ns-eval loads it."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.fields.vanilla_nerf_field import NeRFField
from tests.helpers.ns_configs import run_recording, tiny_radiance_config
from tests.helpers.sp_fields import perturbed_calls

from sp_plugins.nerfstudio.freenerf import (
    OCCLUSION_LOSS,
    OCCLUSION_OUTPUT,
    FreeNeRFField,
    FreeNeRFModelConfig,
    frequency_mask_weights,
    occlusion_loss,
)

BOX = SceneBox(aabb=torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]))
L = 16
"""nerfstudio MipNeRF's position-encoding bands."""


def tiny_model(**overrides):
    from sp_plugins.nerfstudio.runs import method_config

    config = method_config("freenerf-lite").pipeline.model
    config.num_coarse_samples, config.num_importance_samples = 16, 8
    config.mlp_num_layers, config.mlp_layer_width, config.head_mlp_layer_width = 2, 32, 16
    for key, value in overrides.items():
        if key.startswith("sp_"):
            setattr(config.sp, key[3:], value)
        else:
            setattr(config, key, value)
    torch.manual_seed(0)
    return config.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)


def rays(n=32):
    g = torch.Generator().manual_seed(3)
    origins = 4.0 * torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    directions = torch.nn.functional.normalize(0.3 * torch.randn(n, 3, generator=g) - origins, dim=-1)
    return RayBundle(origins=origins, directions=directions, pixel_area=torch.full((n, 1), 1e-4),
                     camera_indices=torch.zeros(n, 1, dtype=torch.long), nears=torch.full((n, 1), 2.0), fars=torch.full((n, 1), 6.0))


def band_weights(mask):
    """``[sin | cos]`` halves, each axis-major: the weight of band k of axis d sits at ``d * L + k``."""
    sin, cos, raw = mask[: 3 * L], mask[3 * L : 6 * L], mask[6 * L :]
    assert torch.equal(sin, cos)
    per_axis = sin.view(3, L)
    assert torch.equal(per_axis[0], per_axis[1]) and torch.equal(per_axis[0], per_axis[2])
    return per_axis[0], raw


def test_registered_with_freenerf_defaults_and_offered_by_sp_train():
    from nerfstudio.plugins.registry import discover_methods

    from sp_plugins.nerfstudio.registration import sp_methods

    methods, descriptions = discover_methods()
    model = methods["freenerf-lite"].pipeline.model
    assert isinstance(model, FreeNeRFModelConfig) and model.sp.enabled is False
    assert (model.freq_reg, model.freq_reg_end, model.occ_reg_mult, model.occ_reg_range, model.occ_reg_samples) == (
        True, 0.7, 0.01, 10, "coarse")
    configs, _, refused = sp_methods({m: methods[m] for m in ("freenerf-lite", "neus-hashgrid")}, descriptions)
    assert "freenerf-lite" not in refused and configs["freenerf-lite"].pipeline.model.sp.enabled is True
    assert configs["freenerf-lite"].method_name == "freenerf-lite"  # ns-eval finds its data manager by the name
    assert "baseline of sp-neus-hashgrid" in refused["neus-hashgrid"]  # real baselines are still refused


@pytest.mark.parametrize(
    "step, bands",
    [
        (0, [0.0] * L),  # only the raw coordinates at the start
        (7, [1.0, 0.6] + [0.0] * (L - 2)),  # 16 * 7 / 70 = 1.6
        (35, [1.0] * 8 + [0.0] * 8),  # half-way: 8 bands, the 9th not yet started
        (69, [1.0] * 15 + [16 * 69 / 70 - 15]),
        (70, [1.0] * L),  # T = 0.7 * 100: all open from here
        (99, [1.0] * L),
    ],
)
def test_the_mask_opens_linearly_over_70_percent_and_never_hides_the_raw_coordinates(step, bands):
    model = tiny_model()
    model.frequency_mask_at(step, 100)
    weights, raw = band_weights(model.encoding.freq_mask)
    assert weights.tolist() == pytest.approx(bands, abs=1e-6)
    assert weights.tolist() == pytest.approx(frequency_mask_weights(L, step, 70.0), abs=1e-6)
    assert torch.equal(raw, torch.ones(3))


def test_the_mask_multiplies_the_encoding_and_freq_reg_off_keeps_every_band():
    model = tiny_model()
    model.frequency_mask_at(0, 100)
    x, cov = torch.rand(5, 3), torch.diag_embed(torch.full((5, 3), 1e-4))
    out = model.encoding(x, covs=cov)
    assert torch.equal(out[:, : 6 * L], torch.zeros(5, 6 * L)) and torch.equal(out[:, 6 * L :], x)
    model.frequency_mask_at(7, 100)
    full = super(type(model.encoding), model.encoding).forward(x, covs=cov)
    assert torch.allclose(model.encoding(x, covs=cov), full * model.encoding.freq_mask)
    off = tiny_model(freq_reg=False)
    off.frequency_mask_at(0, 100)
    assert torch.equal(off.encoding.freq_mask, torch.ones(6 * L + 3))


def test_occlusion_term_is_the_papers_mean_over_all_samples_of_the_first_m():
    density = torch.rand(4, 12, 1)
    term = occlusion_loss(density, 3)
    assert float(term) == pytest.approx(float(density[:, :3].sum() / (4 * 12)))
    beyond, within = density.clone(), density.clone()
    beyond[:, 3:] += 10.0
    within[:, 2] += 1.0
    assert torch.equal(occlusion_loss(beyond, 3), term)
    assert float(occlusion_loss(within, 3)) == pytest.approx(float(term) + 1.0 / 12)


def occlusion_with_bump(model, index=None):
    """The model's unweighted occlusion term on fixed rays, with the density of sample ``index``
    (of every query) raised by 5."""
    get_density = NeRFField.get_density  # the host's, under FreeNeRFField's record of what it returns

    def bumped(self, ray_samples):
        density, embedding = get_density(self, ray_samples)
        if index is not None and index < density.shape[-2]:
            density = density.clone()
            density[..., index, :] += 5.0
        return density, embedding

    NeRFField.get_density = bumped
    try:
        torch.manual_seed(5)  # the uniform sampler's jitter
        return float(model.get_outputs(rays())[OCCLUSION_OUTPUT].detach())
    finally:
        NeRFField.get_density = get_density


def test_the_model_penalises_the_first_m_coarse_samples_only():
    model = tiny_model(occ_reg_range=4)
    model.train()
    plain = occlusion_with_bump(model)
    assert plain > 0
    assert occlusion_with_bump(model, index=4) == pytest.approx(plain, abs=1e-7)  # beyond M: unchanged
    assert occlusion_with_bump(model, index=15) == pytest.approx(plain, abs=1e-7)
    assert occlusion_with_bump(model, index=3) == pytest.approx(plain + 5.0 / 16, rel=1e-5)  # within M: + 5 / K
    assert occlusion_with_bump(model, index=0) == pytest.approx(plain + 5.0 / 16, rel=1e-5)
    model.eval()
    with torch.no_grad():
        assert OCCLUSION_OUTPUT not in model.get_outputs(rays())  # evaluation computes no regulariser


@pytest.mark.parametrize("samples, draws", [("coarse", 1), ("fine", 1), ("coarse", 2)])
def test_it_reads_the_asked_pass_and_averages_sp_draws(samples, draws, monkeypatch):
    overrides = dict(occ_reg_range=3, occ_reg_samples=samples)
    if draws > 1:  # FreeNeRF + SP with two draws per query
        overrides.update(sp_enabled=True, sp_num_samples=draws, sp_alpha0=0.05, sp_schedule="constant")
    model = tiny_model(**overrides)
    model.train()
    model.sp.set_step(0, 10)
    log = []
    get_density = FreeNeRFField.get_density

    def logged(self, ray_samples):
        density, embedding = get_density(self, ray_samples)
        log.append((density.shape[-2], density.detach()))
        return density, embedding

    monkeypatch.setattr(FreeNeRFField, "get_density", logged)
    term = float(model.get_outputs(rays())[OCCLUSION_OUTPUT])
    assert [n for n, _ in log] == [16] * draws + [8] * draws  # coarse pass, then fine
    chosen = log[:draws] if samples == "coarse" else log[draws:]
    assert term == pytest.approx(sum(float(occlusion_loss(d, 3)) for _, d in chosen) / draws, rel=1e-6)


def test_it_trains_and_the_callback_moves_the_mask_every_step(tiny_scene, tmp_path):
    config = tiny_radiance_config("freenerf-lite", tiny_scene, tmp_path, steps=10)
    config.pipeline.model.freq_reg_end = 1.0  # T = 10 steps
    trainer, record = run_recording(config)
    assert len(record) == 10
    for step, (loss, parts, metrics) in enumerate(record):
        assert math.isfinite(loss) and set(parts) == {"rgb_loss_coarse", "rgb_loss_fine", OCCLUSION_LOSS}
        assert metrics["freq_reg_visible_bands"] == pytest.approx(16 * step / 10)
        assert metrics["sp_alpha"] == 0.0  # SP off: FreeNeRF alone
    weights, raw = band_weights(trainer.pipeline.model.encoding.freq_mask)
    assert weights.tolist() == pytest.approx([1.0] * 14 + [0.4, 0.0], abs=1e-6)  # the last step, 9: 14.4 bands
    assert perturbed_calls(trainer.pipeline.model) == 0


def test_a_checkpoint_keeps_its_mask_and_ns_eval_loads_it(tiny_scene, ns_server, tmp_path):
    from tests.helpers.ns_commands import ns_eval

    config = tiny_radiance_config("freenerf-lite", tiny_scene, tmp_path, steps=4)
    config.pipeline.model.freq_reg_end = 1.0  # the last step, 3, sees 12 of the 16 bands
    config.pipeline.datamanager.train_views = 3
    trainer, _ = run_recording(config)
    state = torch.load(next(config.get_checkpoint_dir().glob("step-*.ckpt")), map_location="cpu", weights_only=True)
    saved = state["pipeline"]["_model.field.position_encoding.freq_mask"]
    assert torch.equal(saved, trainer.pipeline.model.encoding.freq_mask) and not bool((saved == 1).all())
    results = ns_eval(config.get_base_dir() / "config.yml", tmp_path, server=ns_server)
    assert math.isfinite(results["psnr"])


def test_a_training_step_of_freenerf_with_sp_has_no_sync_of_ours(tiny_scene, tmp_path):
    """The mask moves on the device, the occlusion term stays a tensor (the counter)."""
    from tests.nerfstudio.test_syncs_ns import steady_state_syncs

    from sp_plugins.core.boundary import dense_fold

    config = tiny_radiance_config("freenerf-lite", tiny_scene, tmp_path, steps=5, enabled=True, alpha0=0.05, end=1.0, seed=0)
    with dense_fold():  # the fold a GPU run takes
        counter = steady_state_syncs(config)
    assert 0 < config.pipeline.model.freq_reg_end < 1  # the counted steps move the mask
    assert not counter.ours(), f"host-device syncs inside sp_plugins per step: {counter.ours()}"
