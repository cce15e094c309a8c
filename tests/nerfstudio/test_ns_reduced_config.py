"""nerfstudio's own smoke procedure for methods, run on every method we register and on the
``sp-train`` configs of nerfstudio's built-in methods.

nerfstudio tests each of its methods by reducing the preset (CPU, 2 iterations, 4 rays, one
image to sample from, the torch implementation, a one-view Blender scene) and running its
``train_loop``. A plugin method should pass the same procedure at its *preset* settings: this
is what caught presets whose SP schedule ended at an absolute step after such a short run. The
``sp-train`` configs (the generic route, ``with_sp``) of the built-in methods that run on a CPU
with Blender data go through it too, with the method's own data manager (worker process and all).

Each run must do more than write a checkpoint file:

- every training loss is finite;
- SP was active when the method has it on: the preconditioner perturbed queries while training
  (and, on a wrapped method, a field counted perturbed calls); a baseline (SP off) perturbed none;
- the checkpoint loads with ``torch.load(..., weights_only=True)``, as nerfstudio's ``ns-eval``
  loads it under torch >= 2.6 (numpy learning rates in a scheduler's state would break it);
- it holds the model's ``sp`` state (``pipeline`` keys ``_model.sp.*``) at the step and total of
  the run, and that state loads back into the preconditioner (a resumed run sees the same alpha).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from tests.helpers.sp_fields import perturbed_calls

from sp_plugins.nerfstudio.runs import method_config, our_methods

METHODS = sorted(our_methods())
BUILTIN = ("nerfacto", "nerfacto-big", "nerfacto-huge", "vanilla-nerf", "tensorf", "phototourism", "dnerf", "mipnerf")
"""nerfstudio's methods whose ``sp-train`` config runs on a CPU with Blender data (``BUILTIN_TRAIN``
of test_with_sp.py but the NeuS family, whose SDFStudio data the reduced procedure does not give)."""
SDF_LAYOUT = ("neus", "neus-facto")
SP_TRAIN = "sp-train:"
OURS_UNDER_SP_TRAIN = ("freenerf-lite",)
"""Our methods with SP off by default that ``sp-train`` offers (``table.SP_OFF_METHODS``)."""


@pytest.fixture(scope="module")
def one_view_scene(tmp_path_factory) -> Path:
    from sp_plugins.data import make_tiny_scene

    scene = make_tiny_scene(tmp_path_factory.mktemp("one-view") / "sphere", mesh="sphere", n_train=1, n_val=1, n_test=1)
    return scene.root / "blender"


def preset(name: str):
    """Our method ``name``, or the ``sp-train`` config of built-in ``sp-train:<method>``."""
    from tests.helpers.ns_configs import sp_train_config

    return sp_train_config(name[len(SP_TRAIN):]) if name.startswith(SP_TRAIN) else method_config(name)


def reduced_config(name: str, data: Path, out: Path):
    """nerfstudio's ``set_reduced_config`` (tests/test_train.py), on our preset."""
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig

    config = preset(name)
    config.machine.num_devices = 1
    config.machine.device_type = "cpu"
    config.max_num_iterations = 2
    config.pipeline.datamanager.dataparser = BlenderDataParserConfig(data=data)
    config.pipeline.datamanager.train_num_images_to_sample_from = 1
    config.pipeline.datamanager.train_num_rays_per_batch = 4
    config.vis = "tensorboard"
    config.output_dir = out
    config.logging.relative_log_dir = Path("logs")
    model = config.pipeline.model
    if hasattr(model, "implementation"):
        model.implementation = "torch"
    if hasattr(model, "num_coarse_samples"):
        model.num_coarse_samples = 4
    if hasattr(model, "num_importance_samples"):
        model.num_importance_samples = 4
    config.viewer.quit_on_train_completion = True
    return config


def test_every_registered_method_is_covered():
    assert len(METHODS) == 13 and {"sp-neus-hashgrid", "sp-mipnerf", "sp-relu-field", "sp-nerfacto", "freenerf-lite"} <= set(METHODS)


def test_sp_train_offers_exactly_our_methods_with_sp_off_that_are_no_baseline():
    from sp_plugins.nerfstudio.table import SP_OFF_METHODS

    assert set(OURS_UNDER_SP_TRAIN) == set(SP_OFF_METHODS)


def test_the_builtin_list_is_the_one_sp_train_trains_end_to_end():
    from tests.nerfstudio import test_with_sp

    assert set(BUILTIN) == set(test_with_sp.BUILTIN_TRAIN) - set(SDF_LAYOUT)


@pytest.fixture
def watched(monkeypatch):
    """Record what ``train_loop`` builds and does: the trainer, every loss, and the
    preconditioner calls made while it was active (a class-level patch: every host calls ``sp(x)``)."""
    from nerfstudio.engine.trainer import Trainer

    from sp_plugins.core import StochasticPreconditioner

    seen = {"trainer": None, "losses": [], "sp_calls": 0}
    setup, iteration, forward = Trainer.setup, Trainer.train_iteration, StochasticPreconditioner.forward

    def setup_(self, *args, **kwargs):
        seen["trainer"] = self
        return setup(self, *args, **kwargs)

    def iteration_(self, step):
        loss, loss_dict, metrics = iteration(self, step)
        seen["losses"].append(float(loss.detach()))
        return loss, loss_dict, metrics

    def forward_(self, x):
        seen["sp_calls"] += int(self.active)
        return forward(self, x)

    monkeypatch.setattr(Trainer, "setup", setup_)
    monkeypatch.setattr(Trainer, "train_iteration", iteration_)
    monkeypatch.setattr(StochasticPreconditioner, "forward", forward_)
    return seen


@pytest.mark.parametrize("name", METHODS + [SP_TRAIN + m for m in BUILTIN + OURS_UNDER_SP_TRAIN])
def test_nerfstudio_reduced_config_trains(name, one_view_scene, tmp_path, watched):
    from nerfstudio.scripts.train import train_loop

    config = reduced_config(name, one_view_scene, tmp_path)
    sp_on = config.pipeline.model.sp.enabled
    assert sp_on or not name.startswith(SP_TRAIN)
    train_loop(local_rank=0, world_size=1, config=config)

    losses = watched["losses"]
    assert len(losses) == 2 and all(math.isfinite(loss) for loss in losses), f"{name}: losses {losses}"
    model = watched["trainer"].pipeline.model
    if sp_on:
        assert watched["sp_calls"] > 0, f"{name}: SP is on but no query was perturbed in 2 iterations"
    else:
        assert watched["sp_calls"] == 0, f"{name}: the baseline (SP off) perturbed queries"
    if name.startswith(SP_TRAIN):
        generic = name[len(SP_TRAIN):] in BUILTIN  # nerfstudio's methods get generated SP classes, ours keep theirs
        assert type(model).__name__.startswith("SPModel__") == generic and perturbed_calls(model) > 0, name

    checkpoints = sorted(config.get_checkpoint_dir().glob("step-*.ckpt"))
    assert checkpoints, f"{name}: the 2-iteration run wrote no checkpoint"
    # ns-eval's load under torch >= 2.6 (weights only); mmap: relu-field-flat's preset writes 2.6 GB
    state = torch.load(checkpoints[-1], map_location="cpu", weights_only=True, mmap=True)
    assert state["step"] == 1, f"{name}: checkpoint of step {state['step']}"
    prefix = "_model.sp."
    sp_state = {key[len(prefix):]: value for key, value in state["pipeline"].items() if key.startswith(prefix)}
    assert {"step", "total_steps"} <= set(sp_state), f"{name}: the checkpoint holds no sp state ({prefix}*)"
    assert int(sp_state["total_steps"]) == 2 and int(sp_state["step"]) in (1, 2), (name, sp_state)
    resumed = model.sp  # a checkpoint's sp state resumes the schedule where the run left it
    resumed.set_step(0, 10)
    resumed.load_state_dict(sp_state)
    assert resumed._step == int(sp_state["step"]) and resumed._total == 2, name
