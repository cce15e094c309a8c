"""What a host must provide is declared by ``SPModelBase`` (issue 45): a host model that leaves a
declared method out is refused when its class is made, and the base runs the "reached" check once,
after the first training step with alpha > 0, for every host (here a toy host of our own)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.model import SPModelBase
from sp_plugins.core import SPConfig
from tests.adapter.toy_host import ToyHostModel, ToySP, ToySPModel, train_steps

DECLARED = ("attach_sp", "check_sp_reached", "sp_preset", "sp_scene_aabb", "sp_training_callback")


@pytest.mark.parametrize("missing", DECLARED)
def test_a_host_model_that_leaves_a_declared_method_out_is_refused_naming_it(missing):
    half = type("Half", (ToySP,), {missing: getattr(SPModelBase, missing) if missing != "sp_preset" else SPModelBase.__dict__[missing]})
    type("HalfMixin", (half,), {})  # still a mixin (no host model yet): fine
    with pytest.raises(TypeError, match=rf"^HalfModel puts SP on a host model but does not implement {missing} "):
        type("HalfModel", (half, ToyHostModel), {})


def test_the_base_builds_the_preconditioner_over_the_hosts_box_and_attaches_it():
    model = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.01, relative_to_diagonal=True, schedule="constant")))
    assert model.field.sp is model.sp and model.sp.scene_diagonal == pytest.approx(12 ** 0.5)
    assert ToySPModel.sp_preset(None).alpha0 == 0.05


def test_the_reached_check_runs_once_after_the_first_step_with_alpha_above_zero():
    model = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.1, schedule="constant", boundary="none")))
    train_steps(model, 4)
    assert model.reach_checks == [0] and model.field.sp_handle.perturbed_calls == 4


def test_the_reached_check_waits_for_alpha_above_zero_and_its_refusal_is_one_line():
    model = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.1, schedule="constant", boundary="none", enabled=False)))
    train_steps(model, 3)
    assert model.reach_checks == []  # SP off: never active, never checked
    model = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.1, schedule="constant", boundary="none")))
    model.field.use_preconditioner(None)  # the host forgot to hand SP to its field
    with pytest.raises(InputError, match=r"^SP reached no field of the toy host in training step 0$"):
        train_steps(model, 2)
    assert model.reach_checks == [0]
