"""Neuralangelo-lite's coarse-to-fine follows Neuralangelo: warm-up, then one level per interval,
the numerical-gradient step 1/res of the finest active level, the curvature weight divided by the
growth factor per added level."""

import math

import pytest
import torch

from sp_plugins.nerfstudio.neus import NeuralangeloLiteModel, coarse_to_fine_schedule


def test_the_schedule_at_neuralangelos_own_settings():
    # 500k steps, warm-up 5000, 4 -> 16 levels one per 5000 steps (all on at 65k)
    def at(step):
        return coarse_to_fine_schedule(step, 5000, 65000, 4, 16)

    assert at(0) == (4, 0, 0.0)
    assert at(2500) == (4, 0, 0.5)  # mid-warm-up: half the curvature weight, still the initial levels
    assert at(4999).active_levels == 4 and at(4999).warmup < 1
    assert at(5000) == (4, 0, 1.0)  # warm-up end
    assert at(9999).active_levels == 4 and at(10000).active_levels == 5
    assert at(35000) == (10, 6, 1.0)  # mid-way: 6 of the 12 levels added
    assert at(64999).active_levels == 15 and at(65000) == (16, 12, 1.0)
    assert at(500000) == (16, 12, 1.0)  # the end
    # a run of a few steps, where the end rounds onto the warm-up: every level at warm-up end
    assert coarse_to_fine_schedule(0, 1, 1, 4, 16) == (4, 0, 0.0)
    assert coarse_to_fine_schedule(1, 1, 1, 4, 16) == (16, 12, 1.0)


def _box():
    from nerfstudio.data.scene_box import SceneBox

    return SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


@pytest.mark.parametrize("stencil", ["6pt", "4pt"])
def test_the_model_sets_levels_step_and_curvature_weight(stencil, tiny_scene, tiny_config, tmp_path):
    config = tiny_config("neuralangelo-lite", tiny_scene, tmp_path, steps=100)
    model_config = config.pipeline.model
    model_config.c2f_warmup, model_config.c2f_end = 0.1, 0.7  # 2 -> 8 levels: one per 10 steps from step 10
    model_config.sdf_field.stencil = stencil
    model: NeuralangeloLiteModel = model_config.setup(scene_box=_box(), num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
    grid = model.field.encoding
    growth = grid.per_level_scale
    assert growth == pytest.approx((64 / 16) ** (1 / 7))  # 8 levels, 16 .. 64
    w0 = model_config.curvature_loss_mult
    per_axis = (lambda eps: eps / math.sqrt(3)) if stencil == "4pt" else (lambda eps: eps)
    expected = {  # step: (active levels, curvature weight)
        0: (2, 0.0), 5: (2, 0.5 * w0), 10: (2, w0), 19: (2, w0), 20: (3, w0 / growth),
        40: (5, w0 / growth**3), 70: (8, w0 / growth**6), 99: (8, w0 / growth**6),
    }
    for step, (levels, weight) in expected.items():
        model.coarse_to_fine_at(step, 100)
        assert int(model.field.active_levels) == levels, step
        res = grid.levels[levels - 1].resolution
        # Neuralangelo's list floor(base * growth^l) + 1; tcnn's vertex count differs by one where that is an integer
        assert abs(res - (math.floor(16 * growth ** (levels - 1)) + 1)) <= 1
        assert float(model.field.fd_step) == pytest.approx(per_axis(1.0 / res), rel=1e-6), step
        assert model.curvature_mult == pytest.approx(weight, rel=1e-6), step
    # the step starts from the coarsest active level and shrinks by the growth factor per level
    model.coarse_to_fine_at(10, 100)
    first = float(model.field.fd_step)
    model.coarse_to_fine_at(20, 100)
    assert first / float(model.field.fd_step) == pytest.approx(growth, rel=0.1)


def test_without_coarse_to_fine_all_levels_finest_step_and_final_weight(tiny_scene, tiny_config, tmp_path):
    config = tiny_config("sp-neuralangelo-lite", tiny_scene, tmp_path, steps=100)
    model = config.pipeline.model.setup(scene_box=_box(), num_train_data=4, metadata={}, device="cpu", grad_scaler=None)
    growth = model.field.encoding.per_level_scale
    model.coarse_to_fine_at(0, 100)
    assert int(model.field.active_levels) == 8
    assert float(model.field.fd_step) == pytest.approx(1.0 / model.field.encoding.levels[7].resolution)
    assert model.curvature_mult == 0.0  # warm-up still applies
    model.coarse_to_fine_at(50, 100)
    assert model.curvature_mult == pytest.approx(config.pipeline.model.curvature_loss_mult / growth**6)
