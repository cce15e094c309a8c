"""thr3ed_atom's ReLU-field learning-rate schedule: restart at every stage, step decay inside it.

At the start of hierarchy stage ``k`` the learning rate restarts at ``lr * stage_gamma^k``; inside
the stage it is multiplied by ``gamma`` at ``first_decay`` after the stage starts and then every
``decay_every``. Both are fractions of the whole training, so a shortened run keeps the original's
ratios: 4 stages x 7000 steps with x0.1 every 3000 steps is ``decay_every = 3/28``; the paper's
SP run (one stage of 28000 steps, decay from step 12000) is ``first_decay = 12/28``.

The stage boundaries are :func:`stage_at`'s, the ones the model upsamples at; the model refuses a
schedule whose stage count differs from its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Type

from nerfstudio.engine.schedulers import Scheduler, SchedulerConfig
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LRScheduler

from sp_plugins.nerfstudio.components.schedulers import FloatLambdaLR


def stage_at(step: int, total_steps: int, stages: int) -> int:
    """Stage of ``step`` when ``total_steps`` are split into ``stages`` equal parts."""
    if total_steps <= 0:
        return stages - 1
    return min(stages - 1, max(0, step) * stages // total_steps)


def stage_start(stage: int, total_steps: int, stages: int) -> int:
    """First step of ``stage`` (the smallest step ``s`` with ``s * stages // total_steps == stage``)."""
    return -(-stage * total_steps // stages)


def staged_lr_factor(step: int, *, total_steps: int, stages: int, decay_every: float, first_decay: Optional[float],
                     gamma: float, stage_gamma: float) -> float:
    """Learning-rate multiplier at ``step`` (see the module docstring)."""
    stage = stage_at(step, total_steps, stages)
    local = max(0, step) - stage_start(stage, total_steps, stages)
    every = max(1, round(decay_every * total_steps))
    first = every if first_decay is None else max(1, round(first_decay * total_steps))
    decays = 0 if local < first else 1 + (local - first) // every
    return stage_gamma**stage * gamma**decays


class StagedStepDecayScheduler(Scheduler):
    config: "StagedStepDecaySchedulerConfig"

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> LRScheduler:
        c = self.config

        def factor(step: int) -> float:
            return staged_lr_factor(step, total_steps=c.max_steps, stages=c.stages, decay_every=c.decay_every,
                                    first_decay=c.first_decay, gamma=c.gamma, stage_gamma=c.stage_gamma)

        return FloatLambdaLR(optimizer, lr_lambda=factor)


@dataclass
class StagedStepDecaySchedulerConfig(SchedulerConfig):
    """Learning rate restarted per hierarchy stage, x ``gamma`` every ``decay_every`` inside it."""

    _target: Type = field(default_factory=lambda: StagedStepDecayScheduler)
    max_steps: int = 28_000
    """Training length the fractions refer to (set it to the run's --max-num-iterations)."""
    stages: int = 4
    """Hierarchy stages (must equal the model's --pipeline.model.hierarchy-stages)."""
    decay_every: float = 3 / 28
    """Fraction of training between two decays (thr3ed_atom: 3000 of 28000 steps)."""
    first_decay: Optional[float] = None
    """Fraction of training from a stage's start to its first decay; None: decay_every."""
    gamma: float = 0.1
    """Multiplier at each decay."""
    stage_gamma: float = 1.0
    """Multiplier of the restart value per stage (thr3ed_atom's script: 0.9)."""

    def __post_init__(self) -> None:
        if self.max_steps < 1 or self.stages < 1:
            raise ValueError(f"max_steps={self.max_steps}, stages={self.stages}: both must be >= 1")
        if not (0 < self.decay_every and math.isfinite(self.decay_every)):
            raise ValueError(f"decay_every={self.decay_every}: a fraction of training > 0")
        if self.first_decay is not None and not self.first_decay > 0:
            raise ValueError(f"first_decay={self.first_decay}: a fraction of training > 0 (or None)")
