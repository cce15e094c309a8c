"""nerfstudio's learning-rate schedulers, with learning rates kept as Python floats.

nerfstudio 1.1.5's ``ExponentialDecayScheduler`` and ``CosineDecayScheduler`` compute their
factor with numpy, so the optimizers' ``lr`` and the schedulers' ``_last_lr`` become numpy
float64 scalars and are saved that way in every checkpoint. torch >= 2.6 loads checkpoints
weights-only by default, and weights-only unpickling refuses numpy scalars
(``Unsupported global: numpy.core.multiarray.scalar``): ``ns-eval``, ``ns-export``,
``ns-render``, the viewer and ``ns-train --load-dir`` all fail on such a checkpoint.

We fix it where the numpy values are made, for our methods only: the schedulers below are the
host's (same factor, same config fields) with every learning rate converted to ``float``, so our
checkpoints hold only tensors and Python numbers. We chose this over allow-listing numpy globals
with ``torch.serialization.add_safe_globals`` when the plugin is imported: that would widen what
every ``torch.load`` in the user's process accepts, for checkpoints of any method, and would
not help a checkpoint loaded where the plugin is not imported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.engine.schedulers import (
    CosineDecayScheduler,
    CosineDecaySchedulerConfig,
    ExponentialDecayScheduler,
    ExponentialDecaySchedulerConfig,
)
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR, LRScheduler

from sp_plugins.adapter.variants import convert


class FloatLambdaLR(LambdaLR):
    """``LambdaLR`` whose learning rates are Python floats whatever type the factor returns."""

    def get_lr(self) -> list[float]:
        return [float(lr) for lr in super().get_lr()]


class _FloatLRs:
    """Mixin for a host scheduler (list it first): its ``LambdaLR`` rebuilt as a
    :class:`FloatLambdaLR` with the same factors. One mixin for both schedulers, since the fix is
    the same whatever the factor.

    The host scheduler already stepped once (setting numpy learning rates); the new one keeps
    its ``initial_lr`` and overwrites every group's ``lr`` with a float at step 0."""

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> LRScheduler:
        host = super().get_scheduler(optimizer, lr_init)  # type: ignore[misc]
        if not isinstance(host, LambdaLR):
            raise TypeError(f"expected nerfstudio's scheduler to be a LambdaLR, got {type(host).__name__}")
        return FloatLambdaLR(optimizer, lr_lambda=list(host.lr_lambdas))


class FloatExponentialDecayScheduler(_FloatLRs, ExponentialDecayScheduler):
    config: "FloatExponentialDecaySchedulerConfig"


@dataclass
class FloatExponentialDecaySchedulerConfig(ExponentialDecaySchedulerConfig):
    """nerfstudio's exponential decay with warm-up; learning rates stored as Python floats."""

    _target: Type = field(default_factory=lambda: FloatExponentialDecayScheduler)


class FloatCosineDecayScheduler(_FloatLRs, CosineDecayScheduler):
    config: "FloatCosineDecaySchedulerConfig"


@dataclass
class FloatCosineDecaySchedulerConfig(CosineDecaySchedulerConfig):
    """nerfstudio's cosine decay with linear warm-up; learning rates stored as Python floats."""

    _target: Type = field(default_factory=lambda: FloatCosineDecayScheduler)


FLOAT_VARIANTS = {
    ExponentialDecaySchedulerConfig: FloatExponentialDecaySchedulerConfig,
    CosineDecaySchedulerConfig: FloatCosineDecaySchedulerConfig,
}


def with_float_schedulers(optimizers: dict) -> dict:
    """``optimizers`` (a trainer config's) with nerfstudio's numpy schedulers swapped for the float
    ones above (same fields, same factors), so checkpoints of a method we wrap load in ``ns-eval``."""
    for entry in optimizers.values():
        scheduler = entry.get("scheduler") if isinstance(entry, dict) else None
        float_cls = FLOAT_VARIANTS.get(type(scheduler))
        if float_cls is not None:
            entry["scheduler"] = convert(scheduler, float_cls)
    return optimizers
