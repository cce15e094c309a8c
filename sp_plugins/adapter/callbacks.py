"""Training callbacks that drive a :class:`StochasticPreconditioner` from a host's trainer.

Host-neutral: a host's callback object is made by the function the model passes
(:meth:`sp_plugins.adapter.model.SPModelBase.sp_training_callback`, ``make(where, func)``), and the
host's optimizer config class is passed to :func:`alpha_grid_optimizer`. What the two hosts' trainers
differ in is read from the callback attributes by name: where the run's length lives (nerfstudio
1.x: ``attributes.trainer.config``; sdfstudio: ``attributes.config``) and the flag that sets it,
which the model passes.
"""

from __future__ import annotations

from typing import Any, Callable, List, Literal, Optional

from sp_plugins.adapter.errors import InputError
from sp_plugins.core import AlphaSchedule, SPConfig, StochasticPreconditioner
from sp_plugins.core.settings import SPSettings

ALPHA_GRID_GROUP = "sp_alpha_grid"
"""Name of the optimizer param group holding a learnable alpha grid."""

Where = Literal["before", "after"]
"""When a training callback runs: before or after every training iteration."""
MakeCallback = Callable[[Where, Callable[[int], None]], Any]
"""``make(where, func)``: the host's training callback calling ``func(step)`` at ``where``."""


def alpha_grid_optimizer(sp_config: SPConfig, adam: Callable[..., Any]) -> dict:
    """The optimizer entry for a learnable alpha grid (``--pipeline.model.sp.alpha-grid True``),
    ``adam`` being the host's ``AdamOptimizerConfig``. Every SP method config carries it: the hosts
    need an entry per parameter group, and an entry without a group (alpha grid off) is never used."""
    return {"optimizer": adam(lr=sp_config.alpha_grid_lr, eps=1e-15), "scheduler": None}


def trainer_total_steps(attributes: Any) -> Optional[int]:
    """Length of one training run as the trainer sees it (``max_num_iterations``), or None."""
    trainer = getattr(attributes, "trainer", None)
    config = trainer.config if trainer is not None else getattr(attributes, "config", None)
    total = getattr(config, "max_num_iterations", None)
    return None if total is None else int(total)


def start_step(attributes: Any) -> Optional[int]:
    """The step training starts at (a resumed run: the checkpoint's step + 1), or None when the
    attributes do not say (sdfstudio's carry no trainer)."""
    start = getattr(getattr(attributes, "trainer", None), "_start_step", None)
    return None if start is None else int(start)


def schedule_problem(config: SPSettings, total_steps: int, steps_flag: str) -> Optional[str]:
    """None when ``config``'s schedule fits a run of ``total_steps``; else the message to show,
    naming the flags a user typed."""
    try:  # only the end is checked against the run (alpha0, its units and final_ratio: SPConfig's own validation)
        AlphaSchedule.resolve(config.schedule, config.alpha0, end=config.end, total_steps=total_steps)
    except ValueError as err:
        return (f"--pipeline.model.sp.end {config.end:g} does not fit {steps_flag} {total_steps} ({err}); "
                f"give --pipeline.model.sp.end as a fraction of training in (0, 1] or a step <= {steps_flag}")
    return None


def sync_alpha_grid_lr(sp: StochasticPreconditioner, attributes: Any) -> None:
    """Give the alpha grid's optimizer the learning rate of ``--pipeline.model.sp.alpha-grid-lr``
    (the single place it is set), also after a resume restored an older one."""
    optimizers = getattr(attributes, "optimizers", None)
    if sp.alpha_grid is None or optimizers is None or ALPHA_GRID_GROUP not in optimizers.optimizers:
        return
    for group in optimizers.optimizers[ALPHA_GRID_GROUP].param_groups:
        group["lr"] = sp.config.alpha_grid_lr
        group["initial_lr"] = sp.config.alpha_grid_lr


def schedule_callback(sp: StochasticPreconditioner, total_steps: Optional[int], make: MakeCallback) -> Any:
    """Before every iteration, move ``sp`` to the trainer's step (with ``total_steps`` None, the
    total saved in ``sp``'s state is kept). A resumed run starts at the checkpoint's step + 1, so it
    continues at the alpha it stopped at."""

    def step_to(step: int) -> None:
        sp.set_step(step, total_steps)

    return make("before", step_to)


def model_schedule_callback(at: Callable[[int, Optional[int]], Any], attributes: Any, make: MakeCallback) -> Any:
    """A schedule of a model's own (FreeNeRF's frequency mask, Neuralangelo's coarse-to-fine) as one
    callback: ``at(step, total)`` is applied now, at the step training starts (0, or a resumed
    run's), and then before every iteration, with the run's length from ``attributes``."""
    total = trainer_total_steps(attributes)
    at(start_step(attributes) or 0, total)

    def update(step: int) -> None:
        at(step, total)

    return make("before", update)


def sp_callbacks(sp: StochasticPreconditioner, attributes: Any, make: MakeCallback, steps_flag: str) -> List[Any]:
    """Everything a model with SP registers: the schedule (checked against the run's length, one
    line naming the flags when it does not fit), plus the alpha grid's learning rate."""
    total = trainer_total_steps(attributes)
    if total is not None:
        problem = schedule_problem(sp.config, total, steps_flag)
        if problem:
            raise InputError(problem)
        start = start_step(attributes)
        # without a start step (sdfstudio), stay at the step the checkpoint loaded (0 on a fresh run);
        # the schedule callback moves to the trainer's step before every iteration either way
        sp.set_step(int(sp.step) if start is None else start, total)
    sync_alpha_grid_lr(sp, attributes)
    return [schedule_callback(sp, total, make)]
