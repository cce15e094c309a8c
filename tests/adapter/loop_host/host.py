"""The plain-loop host: its method table (one preset), its registry entry and its model.

The model is what a research repository's ``train.py`` holds: a field and an :class:`~sp_plugins.SPRun`. The
run's preconditioner is a submodule (``sp``), so the model's ``state_dict`` carries SP's step, total and noise
state; the loop calls ``run.step_pre``, hands the field ``run(x)`` and calls ``run.step_post``."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

import torch
from torch import nn

from sp_plugins import SPConfig, SPRun
from sp_plugins.adapter.hosts import Flags, Host

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RUN_LENGTH = 10
"""Steps of the loop's run (the contract's runs are 10 steps long)."""

PRESET = SPConfig(alpha0=0.02, end=0.3)
"""The loop's one preset (its method table)."""


def preset_for(model_config: Any) -> SPConfig:
    """The table's preset for a model config (every host table has this function)."""
    return dataclasses.replace(PRESET)


HOST = Host(name="loop", packages=("tests",), table=__name__,
            flags=Flags(steps="--steps", device="--device", devices="--devices"))
"""The registry entry (``sp_plugins.adapter.hosts.register(HOST)``)."""


class LoopModel(nn.Module):
    """A field queried at 3-D positions, and SP over the run."""

    steps_flag = HOST.flags.steps

    def __init__(self, sp: SPConfig, total_steps: int = RUN_LENGTH) -> None:
        super().__init__()
        self.field = nn.Sequential(nn.Linear(3, 16), nn.Softplus(), nn.Linear(16, 1))
        self.run = SPRun(sp, total_steps=total_steps, bounds=(BOX[0], BOX[1]))
        self.sp = self.run.preconditioner  # a submodule: in every state_dict
        self.hands_sp_to_field = True

    @classmethod
    def sp_preset(cls, model_config: Any) -> SPConfig:
        return preset_for(model_config)

    def query(self, x: torch.Tensor) -> torch.Tensor:
        """The field at ``x``: at ``x`` moved by SP while training (unless the loop forgot to hand it over)."""
        return self.field(self.run(x) if self.hands_sp_to_field else x)

    def train(self, mode: bool = True) -> "LoopModel":
        super().train(mode)
        self.run.train(mode)
        return self


def train_loop(model: LoopModel, steps: int, observe: Optional[Callable[[int], None]] = None, seed: int = 0) -> None:
    """The loop: ``steps`` steps of a made-up regression, SP at its fixed points."""
    g = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.SGD(model.field.parameters(), lr=1e-2)
    for step in range(steps):
        model.run.step_pre(step)
        model.train()
        x = torch.rand(8, 3, generator=g) * 2 - 1
        loss = (model.query(x) - x.norm(dim=-1, keepdim=True)).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        model.run.step_post(step)
        if observe:
            observe(step)
