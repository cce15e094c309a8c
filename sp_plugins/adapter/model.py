"""The model side of every adapter: the preconditioner, its optimizer group, callbacks, metrics.

Each host's ``SPModel`` (``sp_plugins.nerfstudio.model``, ``sp_plugins.sdfstudio.model``) is this
class plus the host's few differences; it and :class:`SPModelConfig` go first among the bases of
an SP model and its config (the hosts' ``variants`` modules make those subclasses on demand)::

    class SPModelConfig__NeuSModelConfig(SPModelConfig, NeuSModelConfig): ...
    class SPModel__NeuSModel(SPModel, NeuSModel):   # SPModel = SPModelBase + host differences
        def attach_sp(self): ...    # put the seam on the fields the host built

The mixin then

- builds ``self.sp`` (a :class:`StochasticPreconditioner`) from ``config.sp`` before the host's
  modules, bounded by :meth:`SPModelBase.sp_bounds` and with the scene box's diagonal as the scale
  for relative alphas;
- registers it as a submodule, so its step, total and alpha grid are in every checkpoint;
- exposes a learnable alpha grid as the optimizer group ``sp_alpha_grid``;
- drives the schedule from the trainer (step and ``max_num_iterations``);
- logs ``sp_alpha`` with the training metrics.

Both hosts are a package named ``nerfstudio``; this module imports neither at module level.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List

import torch

from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, sp_callbacks
from sp_plugins.core import SPConfig, StochasticPreconditioner


@dataclass
class SPModelConfig:
    """Adds the shared ``sp`` settings (``--pipeline.model.sp.*``) to a model config."""

    sp: SPConfig = field(default_factory=SPConfig)
    """Stochastic preconditioning: perturb query positions while training, alpha annealed to 0."""


def box_diagonal(aabb: torch.Tensor) -> float:
    """Length of the diagonal of the box ``aabb`` ``[2, 3]``."""
    aabb = aabb.detach().float().cpu()
    return float(torch.linalg.norm(aabb[1] - aabb[0]))


class SPModelBase:
    """Mixin for a host ``Model``; list it before the host model class."""

    sp: StochasticPreconditioner
    steps_flag = "--max-num-iterations"
    """The flag that sets the run's length in this host's ``ns-train`` (named in errors)."""

    def sp_bounds(self, aabb: torch.Tensor) -> Any:
        """The box SP reflects into: the scene box here; sdfstudio uses its contraction's range."""
        return aabb.detach().float().cpu()

    def build_preconditioner(self) -> StochasticPreconditioner:
        """``config.sp`` set up over :meth:`sp_bounds`; the total steps come later from the trainer."""
        aabb = self.scene_box.aabb  # type: ignore[attr-defined]
        return self.config.sp.setup(scene_diagonal=box_diagonal(aabb), bounds=self.sp_bounds(aabb), dim=3)  # type: ignore[attr-defined]

    def populate_modules(self) -> None:
        self.sp = self.build_preconditioner()
        self.populate_host_modules()
        self.attach_sp()

    def populate_host_modules(self) -> None:
        """The host model's own ``populate_modules``."""
        super().populate_modules()  # type: ignore[misc]

    def attach_sp(self) -> None:
        """Hand ``self.sp`` to the fields that perturb positions (host and method specific)."""

    def get_param_groups(self) -> Dict[str, List[torch.nn.Parameter]]:
        groups = super().get_param_groups()  # type: ignore[misc]
        if self.sp.alpha_grid is not None:
            groups[ALPHA_GRID_GROUP] = list(self.sp.alpha_grid.parameters())
        return groups

    def get_training_callbacks(self, training_callback_attributes) -> List[Any]:
        callbacks = super().get_training_callbacks(training_callback_attributes)  # type: ignore[misc]
        return list(callbacks) + sp_callbacks(self.sp, training_callback_attributes, self.steps_flag)

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Any]:
        metrics = super().get_metrics_dict(outputs, batch)  # type: ignore[misc]
        if self.training:  # type: ignore[attr-defined]
            metrics["sp_alpha"] = self.sp.alpha
        return metrics
