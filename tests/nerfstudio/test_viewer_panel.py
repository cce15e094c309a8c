"""The viewer's SP panel (:mod:`sp_plugins.nerfstudio.components.viewer_panel`): on every model that
trains with SP and on no other; its "render" control changes the viewer's renders only (nerfstudio's
render thread), never evaluation, the training noise or the reach check's record."""

from __future__ import annotations

import threading

import pytest
import torch

from sp_plugins.nerfstudio.components import viewer_panel as vp
from tests.adapter.contract import NerfstudioDriver

pytest.importorskip("nerfstudio")


def camera():
    from nerfstudio.cameras.cameras import Cameras

    c2w = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4.0]])[None]  # at z = 4, looking down -z
    return Cameras(camera_to_worlds=c2w, fx=12.0, fy=12.0, cx=4.0, cy=4.0, width=8, height=8)


def in_render_thread(fn):
    """``fn()`` run in a thread that is nerfstudio's viewer render thread (a ``RenderStateMachine``)."""
    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    class RenderThread(RenderStateMachine):
        def __init__(self) -> None:  # only the thread: no viewer behind it
            threading.Thread.__init__(self, daemon=True)
            self.result = None

        def run(self) -> None:
            self.result = fn()

    thread = RenderThread()
    thread.start()
    thread.join(120)
    return thread.result


@pytest.fixture(scope="module")
def driver():
    return NerfstudioDriver()


def model_at(driver, step, alpha0=0.2):
    model = driver.build(alpha0=alpha0, schedule="exponential", end=0.5, seed=3)
    driver.train(model, 1, 10)  # the callbacks set the run's length
    model.sp.set_step(step, 10)
    model.eval()
    return model


def test_a_model_with_sp_has_the_panel_and_a_baseline_has_none(driver):
    model = driver.build()
    panel = model.stochastic_preconditioning
    assert isinstance(panel, vp.SPPanel) and panel.e4_render.value == vp.PLAIN and panel.e4_render.options == vp.RENDER_MODES
    assert "gaussian noise, boundary none, 1 draw per query, global alpha" == panel.e3_settings.value
    assert not any(k.startswith("stochastic_preconditioning") for k in model.state_dict())  # checkpoints unchanged
    baseline = driver.build(enabled=False)
    assert getattr(baseline, "stochastic_preconditioning", None) is None


def test_the_viewer_finds_the_panel_where_it_looks_for_controls(driver):
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer_elements import ViewerElement

    model = driver.build()
    found = {path: e.name for path, e in parse_object(model, ViewerElement, "Custom Elements")}
    assert found == {f"Custom Elements/stochastic_preconditioning/{a}": n for a, n in (
        ("e1_alpha", "alpha now"), ("e2_schedule", "schedule"), ("e3_settings", "settings"), ("e4_render", "render"),
        ("e5_draws", "draws"))}, found


def test_the_readouts_follow_training(driver):
    model = driver.build(alpha0=0.2, schedule="linear", end=0.5)
    panel = model.stochastic_preconditioning
    driver.train(model, 1, 10)
    assert panel.e1_alpha.value == "0.2" and panel.e2_schedule.value == "step 0 of 10; alpha reaches 0 at step 5 (0% of the way)"
    driver.train(model, 6, 10)  # steps 0..5 again: alpha 0 at step 5, refreshed at once
    assert panel.e1_alpha.value == "0" and panel.e2_schedule.value == "step 5 of 10; alpha reaches 0 at step 5 (done: SP is off)"


def test_evaluation_is_the_same_with_the_control_in_either_position(driver):
    model = model_at(driver, 0)
    plain = model.get_outputs_for_camera(camera())
    model.stochastic_preconditioning.e4_render.value = vp.SP_VIEW
    assert model.sp.alpha > 0 and not vp.in_viewer_render()
    shown = model.get_outputs_for_camera(camera())
    assert torch.equal(plain["rgb_fine"], shown["rgb_fine"]) and torch.equal(plain["depth_fine"], shown["depth_fine"])


def test_the_viewer_renders_the_field_sp_trains_while_alpha_is_above_zero_and_the_plain_field_after(driver):
    model = model_at(driver, 0, alpha0=1.0)  # an untrained field is smooth: a large alpha for a clear difference
    handle = model.field_fine.sp_handle
    calls, generators = handle.perturbed_calls, {k: g.get_state() for k, g in model.sp._generators.items()}
    plain = in_render_thread(lambda: model.get_outputs_for_camera(camera()))
    model.stochastic_preconditioning.e4_render.value = vp.SP_VIEW
    blurred = in_render_thread(lambda: model.get_outputs_for_camera(camera()))
    again = in_render_thread(lambda: model.get_outputs_for_camera(camera()))
    assert (blurred["rgb_fine"] - plain["rgb_fine"]).abs().max() > 1e-4  # the perturbed field
    assert torch.equal(blurred["rgb_fine"], again["rgb_fine"])  # private noise, fixed seed: a still camera, a still image
    assert handle.perturbed_calls == calls  # not training: nothing for the reach check
    assert {k: g.get_state() for k, g in model.sp._generators.items()}.keys() == generators.keys()
    assert all(torch.equal(model.sp._generators[k].get_state(), s) for k, s in generators.items())  # training noise untouched
    model.sp.set_step(9, 10)  # alpha 0: SP is off, the render is the plain field
    assert model.sp.alpha == 0.0
    assert torch.equal(in_render_thread(lambda: model.get_outputs_for_camera(camera()))["rgb_fine"], plain["rgb_fine"])


def test_the_mean_of_renders_averages_floating_tensors_only():
    """The panel averages its renders with the preconditioner's own K-draw mean (``mean_of_calls``)."""
    from sp_plugins.core.preconditioner import mean_of_calls

    a = {"rgb": torch.zeros(2, 3), "mask": torch.tensor([True, False]), "name": "x"}
    b = {"rgb": torch.ones(2, 3), "mask": torch.tensor([False, False]), "name": "y"}
    renders = iter([a, b])
    mean = mean_of_calls(lambda: next(renders), 2)
    assert torch.equal(mean["rgb"], torch.full((2, 3), 0.5)) and mean["mask"] is a["mask"] and mean["name"] == "x"


def test_a_learnable_alpha_grid_is_an_output_of_renders_only(driver):
    """``sp_alpha_grid``: the grid's expected value along each ray, ``sum_i w_i alpha(x_i)``; at the grid's
    initial value a everywhere that is ``a`` times the ray's accumulation. Renders only (the viewer's
    Output type, ``ns-render``): not in training outputs, and not without a grid."""
    model = driver.build(alpha0=0.05, alpha_grid=True, alpha_grid_init=0.05, schedule="constant", boundary="reflect")
    driver.train(model, 1, 10)
    model.train()
    assert "sp_alpha_grid" not in model(driver._rays(3))
    model.eval()
    outputs = model.get_outputs_for_camera(camera())
    grid = outputs["sp_alpha_grid"]
    assert grid.shape == outputs["accumulation_fine"].shape == (8, 8, 1)
    torch.testing.assert_close(grid, 0.05 * outputs["accumulation_fine"], rtol=1e-4, atol=1e-7)
    assert grid.max() > 0.01
    assert "sp_alpha_grid" not in model_at(driver, 0).get_outputs_for_camera(camera())


def test_the_alpha_grid_output_of_an_sdf_method_uses_its_neus_weights():
    """``sp-neus-hashgrid`` (a field that outputs NeuS alphas, not densities): at the grid's initial value a
    everywhere, ``sp_alpha_grid`` is ``a`` times the SDF's accumulation."""
    import copy
    import dataclasses

    from nerfstudio.configs.method_configs import all_methods
    from nerfstudio.data.scene_box import SceneBox

    config = copy.deepcopy(all_methods["sp-neus-hashgrid"].pipeline.model)
    f = config.sdf_field
    f.num_levels, f.max_res, f.log2_hashmap_size, f.hidden_dim, f.hidden_dim_color, f.geo_feat_dim, f.num_layers = 4, 32, 10, 32, 32, 15, 2
    config.num_samples, config.num_samples_importance, config.num_up_sample_steps, config.num_samples_outside = 8, 8, 1, 4
    config.sp = dataclasses.replace(config.sp, alpha_grid=True, alpha_grid_init=0.05, schedule="constant")
    model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2, metadata={},
                         device="cpu", grad_scaler=None)
    model.eval()
    outputs = model.get_outputs_for_camera(camera())
    torch.testing.assert_close(outputs["sp_alpha_grid"], 0.05 * outputs["accumulation"], rtol=1e-4, atol=1e-7)
    assert outputs["sp_alpha_grid"].max() > 0.01


# -- the readouts' text, exactly (no host needed: they read the preconditioner) ----------------------
def sp_at(step=None, total=None, **settings):
    from sp_plugins.core import SPConfig

    sp = SPConfig(**{"alpha0": 0.2, "schedule": "linear", "end": 0.5, **settings}).setup(total_steps=total, bounds=(-1.0, 1.0))
    if step is not None:
        sp.set_step(step, total)
    return sp


def test_the_schedule_readout_in_each_state():
    assert vp.schedule_text(sp_at()) == "linear from alpha0 0.2; the run's length is not known yet"
    assert vp.schedule_text(sp_at(0, 10)) == "step 0 of 10; alpha reaches 0 at step 5 (0% of the way)"
    assert vp.schedule_text(sp_at(2, 10)) == "step 2 of 10; alpha reaches 0 at step 5 (40% of the way)"
    assert vp.schedule_text(sp_at(4, 10)) == "step 4 of 10; alpha reaches 0 at step 5 (80% of the way)"
    assert vp.schedule_text(sp_at(5, 10)) == "step 5 of 10; alpha reaches 0 at step 5 (done: SP is off)"
    assert vp.schedule_text(sp_at(9, 10)) == "step 9 of 10; alpha reaches 0 at step 5 (done: SP is off)"
    constant = sp_at(3, 10, schedule="constant", alpha0=0.05)
    assert vp.schedule_text(constant) == "constant: alpha 0.05 at step 3 (constant: on for the whole run)"


def test_the_alpha_and_settings_readouts():
    assert [vp.alpha_text(sp_at(s, 10)) for s in (0, 1, 4, 5)] == ["0.2", "0.16", "0.04", "0"]
    assert vp.alpha_text(sp_at(0, 10, alpha0=0.0012345678)) == "0.001235"  # 4 significant digits
    assert vp.settings_text(sp_at(0, 10)) == "gaussian noise, boundary reflect, 1 draw per query, global alpha"
    assert vp.settings_text(sp_at(0, 10, num_samples=4, boundary="none")) == "gaussian noise, boundary none, 4 draws per query, global alpha"
    grid = sp_at(0, 10, alpha_grid=True, alpha_grid_resolution=8)
    assert vp.settings_text(grid) == "gaussian noise, boundary reflect, 1 draw per query, alpha grid 8^3 (replace)"


def test_the_panel_refreshes_every_ten_steps_and_once_when_alpha_reaches_zero():
    sp = sp_at(0, 40, end=0.3)  # linear to 0 at step 12
    refreshed = []
    update = vp.update_callback(type("Panel", (), {"sp": sp, "refresh": lambda self: refreshed.append(sp.progress[0])})())
    for step in range(40):
        sp.set_step(step, 40)
        update(step)
    assert refreshed == [0, 10, 12, 20, 30], refreshed
