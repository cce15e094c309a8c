"""A host of our own, written against ``sp_plugins.adapter`` only: what a third host adapter (or a
user's trainer) provides. Imports no host package, so it also runs where none is importable."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any, Callable, Dict, List

import torch
from torch import nn

from sp_plugins.adapter.callbacks import RunLength, run_length
from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.hosts import Flags, Host
from sp_plugins.adapter.field import SPFieldMixin
from sp_plugins.adapter.model import SPModelBase
from sp_plugins.core import SPConfig

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

# -- the toy host's method table (data, as a host's table.py) and its registry entry -------------------
PRESET = SPConfig(alpha0=0.05, end=0.5)
"""The toy host's one preset."""

def preset_for(model_config: Any) -> SPConfig:
    """The toy table's preset (a host table's ``preset_for``)."""
    return dataclasses.replace(PRESET)


HOST = Host(name="toy", packages=("tests",), table=__name__, flags=Flags(steps="--steps", device="--device", devices="--devices"))
"""What the adapter needs to know of the toy host; :func:`sp_plugins.adapter.hosts.register` adds it
(a host with a distribution names it in an entry point of ``sp_plugins.hosts`` instead)."""


class ToyHostModel(nn.Module):
    """The few methods of a host's ``Model`` the adapter base builds on."""

    def __init__(self, config: Any) -> None:
        super().__init__()
        self.config = config
        self.populate_modules()

    def populate_modules(self) -> None:
        self.field = ToyField()

    def get_param_groups(self) -> Dict[str, List[nn.Parameter]]:
        return {"fields": list(self.field.parameters())}

    def get_training_callbacks(self, attributes: Any) -> List[Any]:
        return []

    def get_metrics_dict(self, outputs: Any, batch: Any) -> Dict[str, Any]:
        return {}


class ToyField(SPFieldMixin, nn.Module):
    """Queried with positions: perturbs them itself (its host has no ray samples)."""

    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.sp_active():
            return self.mean_over_draws(lambda: self.linear(self.sp(x)))
        return self.linear(x)


class ToySP(SPModelBase):
    """The host's half: the methods :class:`SPModelBase` declares abstract."""

    steps_flag = HOST.flags.steps

    def attach_sp(self) -> None:
        self.field.use_preconditioner(self.sp)

    def check_sp_reached(self, step: int) -> None:
        self.reach_checks.append(step)
        if not self.field.sp_handle.perturbed_calls:
            raise InputError(f"SP reached no field of the toy host in training step {step}")

    @classmethod
    def sp_preset(cls, model_config: Any) -> SPConfig:
        return preset_for(model_config)

    def sp_scene_aabb(self) -> torch.Tensor:
        return BOX

    def sp_run_length(self, attributes: Any) -> RunLength:
        return run_length(attributes.config.max_num_iterations)  # the toy trainer's attributes: its config

    def sp_training_callback(self, where: str, func: Callable[[int], None]) -> Any:
        return SimpleNamespace(where=where, func=func)


class ToySPModel(ToySP, ToyHostModel):
    reach_checks: List[int]

    def __init__(self, config: Any) -> None:
        self.reach_checks = []
        super().__init__(config)


def train_steps(model: ToySPModel, steps: int, total: int = 10) -> None:
    """What a host trainer does with the callbacks: before/after each iteration, a step between."""
    callbacks = model.get_training_callbacks(SimpleNamespace(config=SimpleNamespace(max_num_iterations=total)))
    model.train()
    for step in range(steps):
        for c in callbacks:
            if c.where == "before":
                c.func(step)
        model.field(torch.rand(8, 3) * 2 - 1).sum().backward()
        for c in callbacks:
            if c.where == "after":
                c.func(step)
