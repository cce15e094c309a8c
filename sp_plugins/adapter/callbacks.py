"""Training callbacks that drive an :class:`~sp_plugins.core.run.SPRun` from a host's trainer.

Host-neutral: a host's callback object is made by the function the model passes
(:meth:`sp_plugins.adapter.model.SPModelBase.sp_training_callback`, ``make(where, func)``), and the
host's optimizer config class is passed to :func:`alpha_grid_optimizer`. What the hosts' trainers
differ in comes from the host: the run's length and start step
(:meth:`~sp_plugins.adapter.model.SPModelBase.sp_run_length`, a :class:`RunLength`) and the flag
that sets the length (the host's :attr:`~sp_plugins.adapter.hosts.Flags.steps`). Of the callback
attributes only ``optimizers`` is read here (the alpha grid's learning rate), which both hosts name so.
"""

from __future__ import annotations

from typing import Any, Callable, List, Literal, NamedTuple, Optional

from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.hosts import Flags
from sp_plugins.core import AlphaSchedule, SPConfig, StochasticPreconditioner
from sp_plugins.core.run import SPRun
from sp_plugins.core.settings import SPSettings

ALPHA_GRID_GROUP = "sp_alpha_grid"
"""Name of the optimizer param group holding a learnable alpha grid."""

Where = Literal["before", "after"]
"""When a training callback runs: before or after every training iteration."""
MakeCallback = Callable[[Where, Callable[[int], Any]], Any]
"""``make(where, func)``: the host's training callback calling ``func(step)`` at ``where``."""


def alpha_grid_optimizer(sp_config: SPConfig, adam: Callable[..., Any]) -> dict:
    """The optimizer entry for a learnable alpha grid (``--pipeline.model.sp.alpha-grid True``),
    ``adam`` being the host's ``AdamOptimizerConfig``. Every SP method config carries it: the hosts
    need an entry per parameter group, and an entry without a group (alpha grid off) is never used."""
    return {"optimizer": adam(lr=sp_config.alpha_grid_lr, eps=1e-15), "scheduler": None}


class RunLength(NamedTuple):
    """What a host's trainer says of the run it drives (None: it does not say)."""

    total: Optional[int]
    """Training iterations of the run (``max_num_iterations``)."""
    start: Optional[int]
    """The step training starts at (a resumed run: the checkpoint's step + 1)."""


def run_length(total: Any, start: Any = None) -> RunLength:
    """A :class:`RunLength` from the values a host keeps (ints, floats or None)."""
    return RunLength(None if total is None else int(total), None if start is None else int(start))


def schedule_problem(config: SPSettings, total_steps: int, steps_flag: str, sp_flag: str = Flags.sp) -> Optional[str]:
    """None when ``config``'s schedule fits a run of ``total_steps``; else the message to show,
    naming the flags a user typed (the host's run-length flag and the prefix of SP's flags, from its
    :class:`~sp_plugins.adapter.hosts.Flags`)."""
    try:  # only the end is checked against the run (alpha0, its units and final_ratio: SPConfig's own validation)
        AlphaSchedule.resolve(config.schedule, config.alpha0, end=config.end, total_steps=total_steps)
    except ValueError as err:
        return (f"{sp_flag}.end {config.end:g} does not fit {steps_flag} {total_steps} ({err}); "
                f"give {sp_flag}.end as a fraction of training in (0, 1] or a step <= {steps_flag}")
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


def model_schedule_callback(at: Callable[[int, Optional[int]], Any], run: RunLength, make: MakeCallback) -> Any:
    """A schedule of a model's own (FreeNeRF's frequency mask, Neuralangelo's coarse-to-fine) as one
    callback: ``at(step, total)`` is applied now, at the step training starts (0, or a resumed
    run's), and then before every iteration, with the run's length."""
    total = run.total
    at(run.start or 0, total)

    def update(step: int) -> None:
        at(step, total)

    return make("before", update)


def sp_callbacks(sp_run: SPRun, run: RunLength, attributes: Any, make: MakeCallback, steps_flag: str,
                 sp_flag: str = Flags.sp) -> List[Any]:
    """Everything a model with SP registers: ``sp_run``'s fixed points as the host's callbacks (``step_pre`` before
    every iteration, ``step_post``, with the reach check, after it), its length set from the trainer's (checked
    against the schedule: one line naming the flags when it does not fit), and the alpha grid's learning rate (from
    the ``optimizers`` of the host's callback ``attributes``). With no length from the trainer, the total saved in
    the checkpoint is kept; a resumed run starts at the checkpoint's step + 1, so it continues at the alpha it
    stopped at."""
    total = run.total
    if total is not None:
        problem = schedule_problem(sp_run.config, total, steps_flag, sp_flag)
        if problem:
            raise InputError(problem)
        # without a start step (sdfstudio), stay at the step the checkpoint loaded (0 on a fresh run);
        # step_pre moves to the trainer's step before every iteration either way
        sp_run.set_length(total, run.start)
    sync_alpha_grid_lr(sp_run.preconditioner, attributes)
    return [make("before", sp_run.step_pre), make("after", sp_run.step_post)]
