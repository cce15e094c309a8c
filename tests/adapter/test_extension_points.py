"""What a host must provide is declared by ``SPModelBase``: a host model that leaves a
declared method out is refused when its class is made, and the base runs the "reached" check once,
after the first training step with alpha > 0, for every host (here a toy host of our own)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.model import SPModelBase
from sp_plugins.core import SPConfig
from tests.adapter.toy_host import ToyHostModel, ToySP, ToySPModel, train_steps

DECLARED = ("attach_sp", "check_sp_reached", "sp_preset", "sp_run_length", "sp_scene_aabb", "sp_training_callback")


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


def test_the_base_adds_the_alpha_grid_group_and_logs_alpha_only_while_training():
    """The host's groups plus ``sp_alpha_grid`` holding exactly the grid's parameters (none without a
    grid); ``sp_alpha`` in the metrics while training, never in evaluation."""
    plain = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.1, schedule="constant", boundary="none")))
    assert list(plain.get_param_groups()) == ["fields"]
    model = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.1, schedule="constant", boundary="none", alpha_grid=True)))
    groups = model.get_param_groups()
    assert list(groups) == ["fields", "sp_alpha_grid"] and groups["sp_alpha_grid"] == list(model.sp.alpha_grid.parameters())
    train_steps(plain, 1)
    assert plain.get_metrics_dict({}, {}) == {"sp_alpha": plain.sp.alpha} and plain.sp.alpha == pytest.approx(0.1)
    plain.eval()
    assert plain.get_metrics_dict({}, {}) == {}


def test_the_handle_says_what_it_holds():
    """The handle's repr (what a debugging session or a failed check shows)."""
    model = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.1, schedule="constant", boundary="none")))
    assert repr(model.field.sp_handle) == "PreconditionerHandle(set, perturbed_calls=0, reads=[])"
    train_steps(model, 2)
    model.field.sp_handle.reads.add("origins")
    assert repr(model.field.sp_handle) == "PreconditionerHandle(set, perturbed_calls=2, reads=['origins'])"
    model.field.use_preconditioner(None)
    assert repr(model.field.sp_handle) == "PreconditionerHandle(empty, perturbed_calls=0, reads=[])"
