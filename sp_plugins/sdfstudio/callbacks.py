"""Training callbacks that drive a :class:`StochasticPreconditioner` from sdfstudio's trainer
(the same names as :mod:`sp_plugins.nerfstudio.callbacks`)."""

from __future__ import annotations

from typing import List, Optional

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation

from sp_plugins.core import AlphaSchedule, SPConfig, StochasticPreconditioner

ALPHA_GRID_GROUP = "sp_alpha_grid"
"""Name of the optimizer param group holding a learnable alpha grid."""


def trainer_total_steps(attributes: TrainingCallbackAttributes) -> Optional[int]:
    """Length of one training run as sdfstudio's trainer sees it (``max_num_iterations``; its
    callback attributes carry the trainer config, not the trainer)."""
    config = getattr(attributes, "config", None)
    total = getattr(config, "max_num_iterations", None)
    return None if total is None else int(total)


def schedule_callback(sp: StochasticPreconditioner, total_steps: Optional[int]) -> TrainingCallback:
    """Before every iteration, move ``sp`` to the trainer's step (a resumed run starts at the
    checkpoint's step + 1, so it continues at the alpha it stopped at)."""

    def step_to(step: int) -> None:
        sp.set_step(step, total_steps)

    return TrainingCallback(
        where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], func=step_to, update_every_num_iters=1
    )


def sync_alpha_grid_lr(sp: StochasticPreconditioner, attributes: TrainingCallbackAttributes) -> None:
    """Give the alpha grid's optimizer the learning rate of ``--pipeline.model.sp.alpha-grid-lr``."""
    optimizers = attributes.optimizers
    if sp.alpha_grid is None or optimizers is None or ALPHA_GRID_GROUP not in optimizers.optimizers:
        return
    for group in optimizers.optimizers[ALPHA_GRID_GROUP].param_groups:
        group["lr"] = sp.config.alpha_grid_lr
        group["initial_lr"] = sp.config.alpha_grid_lr


def schedule_problem(config: SPConfig, total_steps: int) -> Optional[str]:
    """None when ``config``'s schedule fits a run of ``total_steps``; else the message to show,
    naming the flags a user typed."""
    try:
        AlphaSchedule.resolve(config.schedule, config.alpha0, end=config.end, total_steps=total_steps,
                              scene_diagonal=1.0 if config.relative_to_diagonal else None, final_ratio=config.final_ratio)
    except ValueError as err:
        return (f"--pipeline.model.sp.end {config.end:g} does not fit --trainer.max-num-iterations {total_steps} ({err}); "
                "give --pipeline.model.sp.end as a fraction of training in (0, 1] or a step <= --trainer.max-num-iterations")
    return None


def sp_callbacks(sp: StochasticPreconditioner, attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
    """Everything a model with SP registers: the schedule, plus the alpha grid's learning rate."""
    total = trainer_total_steps(attributes)
    problem = None if total is None else schedule_problem(sp.config, total)
    if problem:
        raise ValueError(problem)
    sync_alpha_grid_lr(sp, attributes)
    return [schedule_callback(sp, total)]
