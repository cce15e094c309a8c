"""The non-finite watch of our nerfstudio models: a run whose loss turned NaN or infinite stops in
one line naming the step and what to try, read only when the trainer logs, saves or ends (no device
sync per step)."""

from __future__ import annotations

from typing import Callable, Dict, List, Optional

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils.misc import step_check

from sp_plugins.adapter.errors import InputError


class NonFiniteWatch:
    """Stops a run whose loss turned NaN or infinite, naming the step and what to try, without a
    device sync per step: each step ORs the losses' finiteness into device tensors; the trainer's
    logging, checkpoint and last steps read them (:meth:`raise_if_diverged`), before any checkpoint of
    a diverged run is written. Under mixed precision GradScaler skips a transient inf, so only a run
    of :attr:`MIXED_PRECISION_RUN` non-finite steps in a row stops it."""

    MIXED_PRECISION_RUN = 10

    def __init__(self) -> None:
        self.bad: Dict[str, torch.Tensor] = {}
        self.first: Optional[torch.Tensor] = None
        self.run: Optional[torch.Tensor] = None
        self.mixed_precision = False

    def update(self, losses: Dict[str, torch.Tensor], step: int) -> None:
        """Record this step's losses (device ops only)."""
        if not losses:
            return
        finite = {name: torch.isfinite(v.detach().float().sum()) for name, v in losses.items()}
        for name, ok in finite.items():
            self.bad[name] = ~ok if name not in self.bad else self.bad[name] | ~ok
        any_bad = ~torch.stack(list(finite.values())).all()
        first = torch.full_like(any_bad, -1, dtype=torch.long) if self.first is None else self.first
        self.first = torch.where((first < 0) & any_bad, step, first)
        run = torch.zeros_like(first) if self.run is None else self.run
        self.run = torch.where(any_bad, run + 1, 0)

    def raise_if_diverged(self, step: int, groups: Callable[[], List[str]],
                          hint: Optional[Callable[[], Optional[str]]] = None) -> None:
        """One device read: raise :class:`InputError` when the run diverged; ``hint`` names a cause the model
        knows of (read only then), put before the generic advice."""
        if self.first is None or self.run is None:
            return
        first, run = (int(v) for v in torch.stack([self.first, self.run]).cpu())
        if first < 0 or (self.mixed_precision and run < self.MIXED_PRECISION_RUN):
            return
        bad = [name for name, flag in self.bad.items() if bool(flag)]
        flags = ", ".join(f"--optimizers.{g.replace('_', '-')}.optimizer.lr" for g in groups()[:3]) or "--optimizers.<group>.optimizer.lr"
        known = hint() if hint is not None else None
        advice = f"likely cause: {known}; otherwise lower" if known else "lower"
        raise InputError(
            f"training step {first}: the loss became NaN or infinite ({', '.join(bad) or 'total'}); the run diverged and stopped "
            f"at step {step} before saving a checkpoint of it: {advice} the learning rate ({flags}, e.g. 10x smaller) or resume "
            "from an earlier checkpoint with --load-dir"
        )


def divergence_callback(watch: NonFiniteWatch, groups: Callable[[], List[str]],
                        attributes: TrainingCallbackAttributes,
                        hint: Optional[Callable[[], Optional[str]]] = None) -> TrainingCallback:
    """Read ``watch`` when the trainer logs, saves, or ends; ``groups``: the optimizer groups a
    divergence message names; ``hint``: a cause the model knows of (:meth:`NonFiniteWatch.raise_if_diverged`)."""
    trainer = getattr(attributes, "trainer", None)
    config = getattr(trainer, "config", None)
    log_every = int(getattr(getattr(config, "logging", None), "steps_per_log", 10) or 10)
    save_every = int(getattr(config, "steps_per_save", 0) or 0)
    last = int(getattr(trainer, "_start_step", 0)) + int(getattr(config, "max_num_iterations", 0) or 0) - 1
    watch.mixed_precision = bool(getattr(config, "mixed_precision", False)) and bool(
        getattr(getattr(trainer, "grad_scaler", None), "is_enabled", lambda: False)())

    def check(step: int) -> None:
        if step_check(step, log_every, run_at_zero=True) or (save_every and step_check(step, save_every)) or step == last:
            watch.raise_if_diverged(step, groups, hint)

    return TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], check, update_every_num_iters=1)
