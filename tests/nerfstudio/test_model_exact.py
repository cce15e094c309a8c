"""The host wiring of SP in our nerfstudio models (sp_plugins.nerfstudio.model), exactly: which losses
the non-finite watch reads and at which step, which optimizer groups its message names, which SP
options a baseline refuses. The mutants of the study (``bench/mutation_study.py``) each test
was written for are listed in ``bench/results/mutation_study/kills.json``; each was shown failing on them."""

from __future__ import annotations

from typing import Dict

import pytest
import torch
from torch import nn

from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP
from sp_plugins.adapter.errors import InputError
from sp_plugins.core import SPConfig
from sp_plugins.nerfstudio.divergence import NonFiniteWatch
from sp_plugins.nerfstudio.model import SPModel, refuse_inert_options

NAN = float("nan")


class _Host(nn.Module):
    """The part of a nerfstudio ``Model`` the wiring calls: its losses and its optimizer groups."""

    losses: Dict[str, torch.Tensor] = {}
    groups: Dict[str, list] = {}

    def get_loss_dict(self, outputs, batch, metrics_dict=None):
        return dict(self.losses)

    def get_param_groups(self):
        return dict(self.groups)


class _Model(SPModel, _Host):
    """SP's model mixin over the stand-in host, built without ``populate_modules`` (no field, no scene):
    only the watch and the preconditioner the wiring reads."""


def _model(step: int = 0) -> _Model:
    model = _Model.__new__(_Model)
    nn.Module.__init__(model)
    model._sp_watch = NonFiniteWatch()
    model.sp = SPConfig(alpha0=0.1, boundary="none").setup(scene_diagonal=1.0, dim=3)
    model.sp.set_step(step, 100)
    return model


def test_the_watch_reads_training_losses_at_sp_s_step_and_never_evaluation_losses():
    """A NaN training loss is recorded at the step SP is at; an evaluation loss, NaN or not, is never
    recorded (``ns-eval`` and the trainer's eval steps must not stop a run)."""
    model = _model(step=7)
    model.losses = {"rgb_loss": torch.tensor(NAN), "interlevel_loss": torch.tensor(0.5)}
    model.eval()
    assert model.get_loss_dict({}, {}) is not None and model._sp_watch.first is None  # evaluation: not read
    model.train()
    losses = model.get_loss_dict({}, {})
    assert set(losses) == {"rgb_loss", "interlevel_loss"}  # the host's losses, handed on unchanged
    assert int(model._sp_watch.first) == 7 and bool(model._sp_watch.bad["rgb_loss"]) and not bool(model._sp_watch.bad["interlevel_loss"])
    with pytest.raises(InputError, match=r"^training step 7: the loss became NaN or infinite \(rgb_loss\)"):
        model._sp_watch.raise_if_diverged(9, model._lr_groups)


def test_finite_training_losses_record_no_divergence():
    model = _model(step=3)
    model.losses = {"rgb_loss": torch.tensor(0.25)}
    model.train()
    model.get_loss_dict({}, {})
    assert int(model._sp_watch.first) == -1
    model._sp_watch.raise_if_diverged(3, model._lr_groups)  # nothing to raise


def test_the_divergence_line_names_every_group_but_sp_s_alpha_grid_in_the_host_s_order():
    """The learning rates a diverged run is told to lower are the host's groups, never SP's alpha grid
    (its own lr flag is ``--pipeline.model.sp.alpha-grid-lr``). The group name compared is an equal
    string that is not the constant itself, as a name read back from a config would be."""
    model = _model()
    grid_name = "".join(["sp_alpha", "_grid"])
    assert grid_name == ALPHA_GRID_GROUP and grid_name is not ALPHA_GRID_GROUP
    # names on both sides of the grid's in sort order: no ordering comparison stands in for inequality
    model.groups = {"proposal_networks": [], grid_name: [], "fields": [], "temporal_distortion": [], "camera_opt": []}
    assert model._lr_groups() == ["proposal_networks", "fields", "temporal_distortion", "camera_opt"]
    model.groups = {"fields": []}
    assert model._lr_groups() == ["fields"]


@pytest.mark.parametrize("num_samples", [1, 2, 4])
def test_a_baseline_refuses_exactly_the_options_that_act_only_through_sp(num_samples):
    """With SP off, ``num_samples`` 1 (the default: one draw) is no option at all and is accepted; 2 or
    more (averaged draws) would be silently ignored and is refused, naming the value."""
    config = SPConfig(enabled=False, num_samples=num_samples)
    if num_samples == 1:
        refuse_inert_options(config)
    else:
        with pytest.raises(InputError, match=rf"^--pipeline\.model\.sp\.num-samples {num_samples} has no effect with SP off"):
            refuse_inert_options(config)
    refuse_inert_options(SPConfig(enabled=True, num_samples=num_samples, alpha_grid=True))  # SP on: both act
    with pytest.raises(InputError, match=r"^--pipeline\.model\.sp\.alpha-grid True has no effect with SP off"):
        refuse_inert_options(SPConfig(enabled=False, num_samples=num_samples, alpha_grid=True))  # the grid named first


class _PositionField(nn.Module):
    """A field (takes ``ray_samples``) whose output is a function of the positions it reads; ``mode``
    "detach" reads them detached (no gradient reaches SP's offset), "zero" multiplies them by 0 (a
    gradient of exactly zero reaches it)."""

    def __init__(self, mode: str = "read") -> None:
        super().__init__()
        self.linear = nn.Linear(3, 1)
        self.mode = mode

    def forward(self, ray_samples):
        x = ray_samples.frustums.get_positions()
        x = x.detach() if self.mode == "detach" else x * 0.0 if self.mode == "zero" else x
        return {"out": self.linear(x)}


# SP's model mixin over a stand-in host model holding one field, in the module the real variants live in
# (sp_host_class: the first base not of sp_plugins, here _Host)
_FieldModel = type("_FieldModel", (SPModel, _Host), {"__module__": "sp_plugins.nerfstudio.variants"})


def _grid_model(mode: str):
    from nerfstudio.cameras.rays import Frustums, RaySamples

    model = _FieldModel.__new__(_FieldModel)
    nn.Module.__init__(model)
    model.field = _PositionField(mode)
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    model.sp = SPConfig(alpha0=0.05, boundary="reflect", alpha_grid=True, alpha_grid_init=0.05).setup(bounds=box, dim=3)
    model.sp.set_step(0, 100)
    model.attach_sp()
    model.train()
    n = 6
    origins = torch.zeros(4, n, 3)
    directions = torch.tensor([0.0, 0.0, 1.0]).expand(4, n, 3)
    starts = torch.linspace(0.1, 0.8, n).view(1, n, 1).expand(4, n, 1)
    samples = RaySamples(Frustums(origins=origins, directions=directions, starts=starts, ends=starts + 0.05,
                                  pixel_area=torch.full((4, n, 1), 1e-4)))
    model.field.forward(samples)["out"].sum().backward()
    return model


@pytest.mark.parametrize("mode", ["detach", "zero"])
def test_an_alpha_grid_that_got_no_gradient_or_a_zero_one_is_refused_after_the_first_step(mode):
    """A learnable alpha grid on a field that detaches the positions it reads (no gradient: ``grad`` None)
    or whose output does not depend on them (a zero gradient) cannot learn: refused in one line after the
    first step, naming the host model and the flag; a field that reads them passes."""
    ok = _grid_model("read")
    assert any(p.grad is not None and bool(p.grad.any()) for p in ok.sp.alpha_grid.parameters())
    ok.check_sp_reached(0)
    model = _grid_model(mode)
    with pytest.raises(InputError, match=r"^--pipeline\.model\.sp\.alpha-grid True cannot learn on tests\.nerfstudio\.test_model_exact\._Host: "
                                         r"no gradient reached the alpha grid in the first training step"):
        model.check_sp_reached(0)


def _plugin_config(host, **flags):
    from types import SimpleNamespace

    return SimpleNamespace(_target=host, sp=SPConfig(boundary="reflect"), **flags)


def test_a_box_boundary_on_a_contracting_model_is_refused_from_its_config_unless_contraction_is_off():
    """Known from the config before the run writes anything: a model whose field contracts space (nerfacto and
    a plugin's subclass of it) gets no box boundary while contraction is on; off (its flag True) it may. A
    plugin's config without the flag is taken as contraction on (what its nerfacto model does)."""
    from nerfstudio.models.nerfacto import NerfactoModel
    from nerfstudio.models.semantic_nerfw import SemanticNerfWModel

    from sp_plugins.nerfstudio.model import refuse_unreachable_settings

    class PluginModel(NerfactoModel):  # a third-party model built on nerfacto, with its own config class
        pass

    line = (r"^--pipeline\.model\.sp\.boundary reflect needs a bounded scene, but NerfactoModel contracts space \(scene "
            r"contraction is on\); pass --pipeline\.model\.sp\.boundary none")
    for config in (_plugin_config(PluginModel), _plugin_config(NerfactoModel, disable_scene_contraction=False)):
        with pytest.raises(InputError, match=line + r" \(or --pipeline\.model\.disable-scene-contraction True\)$"):
            refuse_unreachable_settings(config)
    refuse_unreachable_settings(_plugin_config(PluginModel, disable_scene_contraction=True))  # contraction off
    clamp = _plugin_config(PluginModel)
    clamp.sp = SPConfig(boundary="clamp")  # the other box boundary ("clamp" sorts before "none")
    with pytest.raises(InputError, match=r"^--pipeline\.model\.sp\.boundary clamp needs a bounded scene"):
        refuse_unreachable_settings(clamp)
    none = _plugin_config(PluginModel)
    none.sp = SPConfig(boundary="".join(["no", "ne"]))  # as parsed from a command line: equal, not the literal
    refuse_unreachable_settings(none)
    with pytest.raises(InputError, match=r"but SemanticNerfWModel contracts space .*boundary none$"):  # always on: no flag to name
        refuse_unreachable_settings(_plugin_config(SemanticNerfWModel, disable_scene_contraction=True))


def test_the_run_length_and_start_are_read_where_nerfstudio_keeps_them():
    """nerfstudio 1.x: ``trainer.config.max_num_iterations`` and ``trainer._start_step`` (a resumed run's
    checkpoint step + 1), as ints; a trainer that says nothing gives None, not 0."""
    from types import SimpleNamespace

    trainer = SimpleNamespace(config=SimpleNamespace(max_num_iterations=300.0), _start_step=7)
    assert SPModel.sp_run_length(None, SimpleNamespace(trainer=trainer)) == (300, 7)
    assert SPModel.sp_run_length(None, SimpleNamespace(trainer=SimpleNamespace(config=SimpleNamespace(max_num_iterations=5), _start_step=0))) == (5, 0)
    assert SPModel.sp_run_length(None, SimpleNamespace(trainer=SimpleNamespace(config=SimpleNamespace()))) == (None, None)
    assert SPModel.sp_run_length(None, SimpleNamespace()) == (None, None)


@pytest.mark.parametrize("value", ["yes", "2", "deterministic"])
def test_a_bad_sp_deterministic_is_one_line_under_our_commands(monkeypatch, value):
    """Under ``ns-*`` (the process's own name) a value of ``SP_DETERMINISTIC`` other than auto / 1 / 0 stops
    the build in one line naming it, before anything is held; outside our commands nothing is read."""
    from sp_plugins.nerfstudio.model import hold_deterministic_kernels
    from sp_plugins.patches import registry

    monkeypatch.setenv("SP_DETERMINISTIC", value)
    monkeypatch.setattr("sys.argv", ["python"])
    assert hold_deterministic_kernels(nn.Linear(2, 2)) is False
    monkeypatch.setattr("sys.argv", ["/usr/bin/ns-train"])
    with pytest.raises(InputError) as err:
        hold_deterministic_kernels(nn.Linear(2, 2))
    assert str(err.value) == f"SP_DETERMINISTIC={value!r}: use auto (the default), 1 or 0"
    assert "torch_deterministic" not in registry.held()
