"""The model side of every adapter: the preconditioner, its optimizer group, callbacks, metrics.

Each host's ``SPModel`` (``sp_plugins.nerfstudio.model``, ``sp_plugins.sdfstudio.model``) is this
class plus what that host must provide, declared here as abstract methods (in the manner of
nerfstudio's ``Model.get_outputs``): :meth:`SPModelBase.attach_sp`, :meth:`SPModelBase.check_sp_reached`,
:meth:`SPModelBase.sp_preset`, :meth:`SPModelBase.sp_scene_aabb`, :meth:`SPModelBase.sp_training_callback`
and :meth:`SPModelBase.sp_run_length`, plus ``steps_flag`` (the host's registry entry names it).
It and :class:`SPModelConfig` go first among the bases of an SP model and its config (the hosts'
``variants`` modules make those subclasses on demand)::

    class SPModelConfig__NeuSModelConfig(SPModelConfig, NeuSModelConfig): ...
    class SPModel__NeuSModel(SPModel, NeuSModel):   # SPModel = SPModelBase + the host's methods
        ...

The base then

- builds ``self.sp`` (a :class:`StochasticPreconditioner`) from ``config.sp`` before the host's
  modules, bounded by :meth:`SPModelBase.sp_bounds` and with the scene box's diagonal as the scale
  for relative alphas, and hands it to the host's fields (:meth:`SPModelBase.attach_sp`);
- registers it as a submodule, so its step, total and alpha grid are in every checkpoint;
- exposes a learnable alpha grid as the optimizer group ``sp_alpha_grid``;
- wraps it in ``self.sp_run``, an :class:`~sp_plugins.core.run.SPRun` (what a plain training loop uses), whose
  fixed points the host's trainer calls as callbacks: the schedule from the trainer's step and
  ``max_num_iterations`` before every iteration, the host's "reached" check once, after the first training step
  with alpha > 0;
- logs ``sp_alpha`` with the training metrics.

This module imports no host: what it needs of one comes through the declared methods.
"""

from __future__ import annotations

import abc
import inspect
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Tuple

import torch

from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, RunLength, Where, sp_callbacks
from sp_plugins.adapter.hosts import Flags
from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.core.run import SPRun


@dataclass
class SPModelConfig:
    """Adds the shared ``sp`` settings (``--pipeline.model.sp.*``) to a model config."""

    sp: SPConfig = field(default_factory=SPConfig)
    """Stochastic preconditioning: perturb query positions while training, alpha annealed to 0."""


def box_diagonal(aabb: torch.Tensor) -> float:
    """Length of the diagonal of the box ``aabb`` ``[2, 3]``."""
    aabb = aabb.detach().float().cpu()
    return float(torch.linalg.norm(aabb[1] - aabb[0]))


def unimplemented(cls: type) -> Tuple[str, ...]:
    """The abstract methods of :class:`SPModelBase` that ``cls`` leaves unimplemented."""
    return tuple(name for name in sorted(dir(cls))
                 if getattr(inspect.getattr_static(cls, name, None), "__isabstractmethod__", False))


class SPModelBase:
    """Mixin for a host ``Model``; list it before the host model class.

    A class that puts this mixin on a host model (an ``nn.Module``) must implement every method
    marked abstract here; one that does not is refused when it is defined (a ``TypeError`` naming
    the method), not at its first training step. (``abc.ABCMeta`` cannot be used: host models'
    metaclass is torch's ``type``, and our variants are made with ``type(...)``.)"""

    sp: StochasticPreconditioner
    sp_run: SPRun
    config: Any  # the host model's (its config holds an ``sp`` field)
    training: bool  # nn.Module's
    steps_flag: str
    """The flag that sets the run's length in this host's training command (named in errors): the
    host's model sets it from its registry entry (:attr:`sp_plugins.adapter.hosts.Flags.steps`)."""
    sp_flag: str = Flags.sp
    """The prefix of SP's flags in this host's training command (named in errors; its :attr:`Flags.sp`)."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if not issubclass(cls, torch.nn.Module):
            return
        missing = unimplemented(cls)
        if missing:
            raise TypeError(f"{cls.__qualname__} puts SP on a host model but does not implement {', '.join(missing)} "
                            "(the methods SPModelBase declares abstract)")
        if not isinstance(getattr(cls, "steps_flag", None), str):
            raise TypeError(f"{cls.__qualname__} puts SP on a host model but sets no steps_flag "
                            "(its host's Flags.steps, from the host registry)")

    # -- what a host provides ----------------------------------------------------------------------
    @abc.abstractmethod
    def attach_sp(self) -> None:
        """Hand ``self.sp`` to the fields the host built (after its ``populate_modules``); raise
        :class:`~sp_plugins.adapter.errors.InputError` when no field can be reached."""

    @abc.abstractmethod
    def check_sp_reached(self, step: int) -> None:
        """Raise :class:`~sp_plugins.adapter.errors.InputError` unless a field query *read* positions
        that SP *moved* in the training step ``step`` that just ran (the first with alpha > 0; the
        base calls this once per run)."""

    @classmethod
    @abc.abstractmethod
    def sp_preset(cls, model_config: Any) -> SPConfig:
        """A fresh copy of the SP settings ``with_sp`` gives the host ``model_config`` (its paper
        preset, or :data:`sp_plugins.adapter.presets.DEFAULT`)."""

    @abc.abstractmethod
    def sp_scene_aabb(self) -> torch.Tensor:
        """The scene's box ``[2, 3]`` (min, max) in the units SP's alpha is given in."""

    @abc.abstractmethod
    def sp_training_callback(self, where: Where, func: Callable[[int], None]) -> Any:
        """A host training callback that calls ``func(step)`` ``"before"`` or ``"after"`` every
        training iteration."""

    @abc.abstractmethod
    def sp_run_length(self, attributes: Any) -> RunLength:
        """The run's length and start step, read from the host's training callback ``attributes``
        where that host's trainer keeps them (each host keeps them elsewhere)."""

    # -- shared by every host ----------------------------------------------------------------------
    @classmethod
    def sp_host_class(cls) -> type:
        """The host model class this SP class is built on (the first base not of sp_plugins)."""
        return next(c for c in cls.__mro__ if not c.__module__.startswith("sp_plugins."))

    def sp_bounds(self, aabb: torch.Tensor) -> Any:
        """The box SP reflects into: the scene box here; sdfstudio uses its contraction's range."""
        return aabb.detach().float().cpu()

    def build_preconditioner(self) -> StochasticPreconditioner:
        """``config.sp`` set up over :meth:`sp_bounds`; the total steps come later from the trainer."""
        aabb = self.sp_scene_aabb()
        return self.config.sp.setup(scene_diagonal=box_diagonal(aabb), bounds=self.sp_bounds(aabb), dim=3)

    def populate_modules(self) -> None:
        self.sp = self.build_preconditioner()
        # SP's lifecycle over the run (schedule, reach check, alpha): the same object a plain loop uses, around the
        # preconditioner this model keeps as its submodule (its state stays in the host's checkpoint, ``sp.*``); the
        # host's optimizer steps the alpha grid's group, and the host's train() / eval() own the mode
        self.sp_run = SPRun.over(self.sp, reach=self.check_sp_reached, sets_mode=False, alpha_grid_optimizer=False)
        self.populate_host_modules()
        self.attach_sp()

    def populate_host_modules(self) -> None:
        """The host model's own ``populate_modules``."""
        super().populate_modules()  # type: ignore[misc]  # the host model's (next in the MRO)

    def get_param_groups(self) -> Dict[str, List[torch.nn.Parameter]]:
        groups = super().get_param_groups()  # type: ignore[misc]  # the host model's (next in the MRO)
        if self.sp.alpha_grid is not None:
            groups[ALPHA_GRID_GROUP] = list(self.sp.alpha_grid.parameters())
        return groups

    def get_training_callbacks(self, training_callback_attributes) -> List[Any]:
        callbacks = super().get_training_callbacks(training_callback_attributes)  # type: ignore[misc]  # the host model's (next in the MRO)
        run = self.sp_run_length(training_callback_attributes)
        return list(callbacks) + sp_callbacks(self.sp_run, run, training_callback_attributes, self.sp_training_callback,
                                              self.steps_flag, self.sp_flag)

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Any]:
        metrics = super().get_metrics_dict(outputs, batch)  # type: ignore[misc]  # the host model's (next in the MRO)
        if self.training:
            metrics["sp_alpha"] = self.sp_run.alpha
        return metrics
