"""Training callbacks that drive a :class:`StochasticPreconditioner` from nerfstudio's trainer."""

from __future__ import annotations

from typing import List, Optional

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation

from sp_plugins.core import StochasticPreconditioner
from sp_plugins.nerfstudio.errors import InputError

ALPHA_GRID_GROUP = "sp_alpha_grid"
"""Name of the optimizer param group holding a learnable alpha grid."""


def alpha_grid_optimizer(sp_config) -> dict:
    """The optimizer entry for a learnable alpha grid (``--pipeline.model.sp.alpha-grid True``).
    Every method config carries it: nerfstudio needs an entry per parameter group, and an entry
    without a group (alpha grid off) is never used."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig

    return {"optimizer": AdamOptimizerConfig(lr=sp_config.alpha_grid_lr, eps=1e-15), "scheduler": None}


def trainer_total_steps(attributes: TrainingCallbackAttributes) -> Optional[int]:
    """Length of one training run as the trainer sees it (``max_num_iterations``)."""
    trainer = attributes.trainer
    return None if trainer is None else int(trainer.config.max_num_iterations)


def schedule_callback(sp: StochasticPreconditioner, total_steps: Optional[int]) -> TrainingCallback:
    """Before every iteration, move ``sp`` to the trainer's step.

    ``total_steps`` is the trainer's ``max_num_iterations``; when None (no trainer) the total saved
    in ``sp``'s state is kept. A resumed run calls this with the checkpoint's step + 1, so it
    continues at the alpha it stopped at.
    """

    def step_to(step: int) -> None:
        sp.set_step(step, total_steps)

    return TrainingCallback(
        where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], func=step_to, update_every_num_iters=1
    )


def sync_alpha_grid_lr(sp: StochasticPreconditioner, attributes: TrainingCallbackAttributes) -> None:
    """Give the alpha grid's optimizer the learning rate of ``--pipeline.model.sp.alpha-grid-lr``
    (the single place it is set), also after a resume restored an older one."""
    optimizers = attributes.optimizers
    if sp.alpha_grid is None or optimizers is None or ALPHA_GRID_GROUP not in optimizers.optimizers:
        return
    for group in optimizers.optimizers[ALPHA_GRID_GROUP].param_groups:
        group["lr"] = sp.config.alpha_grid_lr
        group["initial_lr"] = sp.config.alpha_grid_lr


def sp_callbacks(sp: StochasticPreconditioner, attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
    """Everything a model with SP registers: the schedule, plus the alpha grid's learning rate."""
    total = trainer_total_steps(attributes)
    if total is not None:
        trainer = attributes.trainer
        try:
            sp.set_step(int(getattr(trainer, "_start_step", 0)), total)
        except ValueError as err:  # name the flags a user typed, not the library's arguments
            raise InputError(
                f"--pipeline.model.sp.end {sp.config.end:g} does not fit --max-num-iterations {total} ({err}); "
                "give --pipeline.model.sp.end as a fraction of training in (0, 1] or a step <= --max-num-iterations"
            ) from None
    sync_alpha_grid_lr(sp, attributes)
    return [schedule_callback(sp, total)]
