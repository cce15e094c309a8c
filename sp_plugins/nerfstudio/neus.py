"""NeuS and Neuralangelo-lite models with the shared SP settings.

- :class:`SPNeuSModel`: nerfstudio's NeuS whose field perturbs its queries (see
  :mod:`sp_plugins.nerfstudio.sdf_field`); ``sp.enabled=False`` is the plain baseline. The cosine
  annealing of NeuS ends at a fraction of training instead of a fixed 50k steps, so short runs
  anneal too.
- :class:`NeuralangeloLiteModel`: the same with a hash grid, numerical gradients, an eikonal and a
  curvature loss, and Neuralangelo's coarse-to-fine scheme (grid levels switched on one by one,
  the finite-difference step shrinking with the finest active level, the curvature weight
  shrinking with it). ``coarse_to_fine=False`` uses all levels and the finest step from step 0
  (what the SP variant does).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Type

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.neus import NeuSModel, NeuSModelConfig

from sp_plugins.nerfstudio.callbacks import trainer_total_steps
from sp_plugins.nerfstudio.model import SPModel, SPModelConfig
from sp_plugins.nerfstudio.sdf_field import LAPLACIAN, SPSDFField, SPSDFFieldConfig


def _steps(fraction_or_steps: float, total: int) -> int:
    """A fraction of training (<= 1) or an absolute step count (> 1) as steps."""
    return max(1, round(fraction_or_steps * total)) if fraction_or_steps <= 1 else int(fraction_or_steps)


@dataclass
class SPNeuSModelConfig(SPModelConfig, NeuSModelConfig):
    """NeuS with stochastic preconditioning at the SDF field's queries."""

    _target: Type = field(default_factory=lambda: SPNeuSModel)
    sdf_field: SPSDFFieldConfig = field(default_factory=SPSDFFieldConfig)
    """The SDF field (NeuS: frequency encoding only; hash grid with use_grid_feature)."""
    cos_anneal_end: float = 0.5
    """NeuS cosine annealing reaches 1 here: a fraction of training (<= 1) or a step count."""


class SPNeuSModel(SPModel, NeuSModel):
    config: SPNeuSModelConfig
    field: SPSDFField

    def populate_modules(self) -> None:
        from sp_plugins.patches.nerfstudio_marching_cubes import install_cpu_marching_cubes

        super().populate_modules()
        install_cpu_marching_cubes()  # ns-export marching-cubes builds this model, then meshes it

    def attach_sp(self) -> None:
        self.field.use_preconditioner(self.sp)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        total = trainer_total_steps(training_callback_attributes)
        if total is not None:
            self.anneal_end = _steps(self.config.cos_anneal_end, total)
        return super().get_training_callbacks(training_callback_attributes)


@dataclass
class NeuralangeloLiteModelConfig(SPNeuSModelConfig):
    """Neuralangelo on NeuS's renderer: hash grid, numerical gradients, curvature loss, coarse-to-fine."""

    _target: Type = field(default_factory=lambda: NeuralangeloLiteModel)
    sdf_field: SPSDFFieldConfig = field(
        default_factory=lambda: SPSDFFieldConfig(
            use_grid_feature=True, numerical_gradients=True, num_layers=2, num_layers_color=2, hidden_dim=256, geo_feat_dim=256
        )
    )
    eikonal_loss_mult: float = 0.1
    curvature_loss_mult: float = 5e-4
    """Weight of the mean |Laplacian| at the coarse-to-fine start; scaled by step / start step."""
    curvature_warmup: float = 0.01
    """Linear warm-up of the curvature weight: a fraction of training or a step count."""
    coarse_to_fine: bool = True
    """Switch grid levels on progressively and shrink the finite-difference step with them."""
    c2f_init_levels: int = 4
    """Active grid levels at step 0."""
    c2f_end: float = 0.12
    """All levels are active from here on: a fraction of training (Neuralangelo: 60k of 500k) or a step."""

    def __post_init__(self) -> None:
        if not 1 <= self.c2f_init_levels <= self.sdf_field.num_levels:
            raise ValueError(f"c2f_init_levels={self.c2f_init_levels}: must be in [1, num_levels={self.sdf_field.num_levels}]")
        if not (self.sdf_field.use_grid_feature and self.sdf_field.numerical_gradients):
            raise ValueError("neuralangelo-lite needs sdf_field.use_grid_feature=True and numerical_gradients=True")


class NeuralangeloLiteModel(SPNeuSModel):
    config: NeuralangeloLiteModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        self.curvature_mult = 0.0
        self.coarse_to_fine_at(0, None)

    def coarse_to_fine_at(self, step: int, total: "int | None") -> None:
        """Set active levels, finite-difference step and curvature weight for ``step``."""
        c = self.config
        levels = c.sdf_field.num_levels
        if c.coarse_to_fine and total is not None:
            per_level = max(1, _steps(c.c2f_end, total) // max(1, levels - c.c2f_init_levels))
            active = min(levels, c.c2f_init_levels + step // per_level)
        elif c.coarse_to_fine:
            active = c.c2f_init_levels
        else:
            active = levels
        self.field.set_active_levels(active)
        fd = c.sdf_field.fd_step if c.sdf_field.fd_step is not None else self.field.level_cell_size(active - 1)
        self.field.set_fd_step(fd)
        reference = self.field.level_cell_size(c.c2f_init_levels - 1)
        warm = 1.0 if total is None else min(1.0, step / _steps(c.curvature_warmup, total))
        self.curvature_mult = c.curvature_loss_mult * warm * min(1.0, fd / reference)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        total = trainer_total_steps(training_callback_attributes)
        start = int(getattr(training_callback_attributes.trainer, "_start_step", 0))
        self.coarse_to_fine_at(start, total)

        def update(step: int) -> None:
            self.coarse_to_fine_at(step, total)

        return callbacks + [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], update, update_every_num_iters=1)
        ]

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        losses = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training and self.curvature_mult > 0:
            lap = outputs["field_outputs"].get(LAPLACIAN)
            if lap is not None:
                losses["curvature_loss"] = lap.abs().mean() * self.curvature_mult
        return losses

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        metrics = super().get_metrics_dict(outputs, batch)
        if self.training:
            metrics["active_levels"] = self.field.encoding.active_levels  # Python mirrors: no GPU sync per step
            metrics["fd_step"] = self.field._fd_step
        return metrics


__all__ = ["NeuralangeloLiteModel", "NeuralangeloLiteModelConfig", "SPNeuSModel", "SPNeuSModelConfig"]
