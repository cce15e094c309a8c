"""What every nerfstudio model with stochastic preconditioning shares.

Put :class:`SPModelConfig` and :class:`SPModel` first among the bases of a host model's config
and model::

    @dataclass
    class SPNeuSModelConfig(SPModelConfig, NeuSModelConfig):
        _target: Type = field(default_factory=lambda: SPNeuSModel)

    class SPNeuSModel(SPModel, NeuSModel):
        def attach_sp(self):            # hand the preconditioner to whatever perturbs positions
            self.field.use_preconditioner(self.sp)

The mixin then

- builds ``self.sp`` (a :class:`StochasticPreconditioner`) from ``config.sp`` before the host's
  modules, with the scene box as bounds and its diagonal as the scale for relative alphas;
- registers it as a submodule, so its step, total and alpha grid are in every checkpoint;
- exposes a learnable alpha grid as the optimizer group ``sp_alpha_grid``;
- drives the schedule from the trainer (step and ``max_num_iterations``);
- builds LPIPS without downloads, and leaves it out of the state dict;
- logs ``sp_alpha`` with the training metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List

import torch
from torch.nn import Parameter

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes

from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.nerfstudio.callbacks import ALPHA_GRID_GROUP, sp_callbacks
from sp_plugins.nerfstudio.errors import InputError
from sp_plugins.nerfstudio.lpips import detach_lpips, drop_missing_lpips, offline_lpips


@dataclass
class SPModelConfig:
    """Adds the shared ``sp`` settings (``--pipeline.model.sp.*``) to a model config."""

    sp: SPConfig = field(default_factory=SPConfig)
    """Stochastic preconditioning: perturb query positions while training, alpha annealed to 0."""


def refuse_inert_options(config: SPConfig) -> None:
    """With SP off (a baseline), options that only act through SP would be silently ignored:
    refuse them, naming the flag."""
    if config.enabled:
        return
    inert = [flag for flag, on in (("alpha-grid True", config.alpha_grid), (f"num-samples {config.num_samples}", config.num_samples > 1)) if on]
    if inert:
        raise InputError(
            f"--pipeline.model.sp.{inert[0]} has no effect with SP off (--pipeline.model.sp.enabled False, the "
            "baseline); pass --pipeline.model.sp.enabled True or train the sp- variant of this method"
        )


def build_preconditioner(config: SPConfig, aabb: torch.Tensor) -> StochasticPreconditioner:
    """A preconditioner over the scene box ``aabb`` ``[2, 3]``; the total steps come later from
    the trainer."""
    refuse_inert_options(config)
    aabb = aabb.detach().float().cpu()
    diagonal = float(torch.linalg.norm(aabb[1] - aabb[0]))
    return config.setup(scene_diagonal=diagonal, bounds=aabb, dim=3)


class SPModel:
    """Mixin for a nerfstudio ``Model``; list it before the host model class."""

    sp: StochasticPreconditioner

    def populate_modules(self) -> None:
        self.sp = build_preconditioner(self.config.sp, self.scene_box.aabb)  # type: ignore[attr-defined]
        with offline_lpips():
            super().populate_modules()  # type: ignore[misc]
        detach_lpips(self)  # type: ignore[arg-type]
        self.attach_sp()

    def attach_sp(self) -> None:
        """Hand ``self.sp`` to the fields or samplers that perturb positions (host specific)."""

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = super().get_param_groups()  # type: ignore[misc]
        if self.sp.alpha_grid is not None:
            groups[ALPHA_GRID_GROUP] = list(self.sp.alpha_grid.parameters())
        return groups

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)  # type: ignore[misc]
        return list(callbacks) + sp_callbacks(self.sp, training_callback_attributes)

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        metrics = super().get_metrics_dict(outputs, batch)  # type: ignore[misc]
        if self.training:  # type: ignore[attr-defined]
            metrics["sp_alpha"] = self.sp.alpha
        return metrics

    def get_image_metrics_and_images(self, outputs, batch):
        metrics, images = super().get_image_metrics_and_images(outputs, batch)  # type: ignore[misc]
        return drop_missing_lpips(self, metrics), images  # type: ignore[arg-type]
