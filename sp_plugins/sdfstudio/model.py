"""What every sdfstudio model with stochastic preconditioning shares (the same names as
:mod:`sp_plugins.nerfstudio.model`).

Put :class:`SPModelConfig` and :class:`SPModel` first among the bases of a host model's config
and model (:mod:`sp_plugins.sdfstudio.variants` does this for every sdfstudio SDF model, with
:class:`SDFFieldSPModel`, whose ``attach_sp`` hands the preconditioner to the SDF field)::

    @dataclass
    class SPNeuSModelConfig(SPModelConfig, NeuSModelConfig):
        _target: Type = field(default_factory=lambda: SPNeuSModel)

    class SPNeuSModel(SPModel, NeuSModel):
        def attach_sp(self):            # hand the preconditioner to whatever perturbs positions
            self.field.use_preconditioner(self.sp)

The mixin then

- builds ``self.sp`` (a :class:`StochasticPreconditioner`) before the host's modules, reflecting
  into the scene contraction's range and scaling relative alphas by the scene box's diagonal;
- registers it as a submodule, so its step, total and alpha grid are in every checkpoint;
- exposes a learnable alpha grid as the optimizer group ``sp_alpha_grid``;
- drives the schedule from the trainer (step and ``max_num_iterations``);
- logs ``sp_alpha`` with the training metrics.

(LPIPS without downloads is a patch here, :mod:`sp_plugins.patches.sdfstudio_lpips`, because
sdfstudio's own ns-eval builds the same models.)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from torch.nn import Parameter

from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.sdfstudio.callbacks import ALPHA_GRID_GROUP, sp_callbacks
from sp_plugins.sdfstudio.sdf_field import CONTRACTED_BOUNDS


@dataclass
class SPModelConfig:
    """Adds the shared ``sp`` settings (``--pipeline.model.sp.*``) to a model config."""

    sp: SPConfig = field(default_factory=SPConfig)
    """Stochastic preconditioning: perturb query positions while training, alpha annealed to 0."""


def build_preconditioner(config: SPConfig, aabb: torch.Tensor) -> StochasticPreconditioner:
    """A preconditioner over sdfstudio's contracted space; relative alphas use the diagonal of
    the scene box ``aabb`` ``[2, 3]``. The total steps come later from the trainer."""
    aabb = aabb.detach().float().cpu()
    diagonal = float(torch.linalg.norm(aabb[1] - aabb[0]))
    return config.setup(scene_diagonal=diagonal, bounds=CONTRACTED_BOUNDS, dim=3)


class SPModel:
    """Mixin for an sdfstudio ``Model``; list it before the host model class."""

    sp: StochasticPreconditioner

    def populate_modules(self) -> None:
        self.sp = build_preconditioner(self.config.sp, self.scene_box.aabb)  # type: ignore[attr-defined]
        super().populate_modules()  # type: ignore[misc]
        self.attach_sp()

    def attach_sp(self) -> None:
        """Hand ``self.sp`` to the fields that perturb positions (host specific)."""

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


class SDFFieldSPModel(SPModel):
    """:class:`SPModel` for any sdfstudio ``SurfaceModel``: the preconditioner goes to the SDF
    field ``self.field`` that ``SurfaceModel.populate_modules`` builds from ``config.sdf_field``
    (an :class:`~sp_plugins.sdfstudio.sdf_field.SPSDFFieldConfig` in every SP model config).
    List it before the host model class (the SP model variants of
    :mod:`sp_plugins.sdfstudio.variants` are ``(SDFFieldSPModel, HostModel)``)."""

    def attach_sp(self) -> None:
        from sp_plugins.sdfstudio.sdf_field import SPSDFField

        field = getattr(self, "field", None)
        if not isinstance(field, SPSDFField):
            raise TypeError(
                f"{type(self).__name__}: SP needs the SDF field built from an SPSDFFieldConfig, got "
                f"{type(field).__name__} (the model config's sdf_field must be SPSDFFieldConfig)"
            )
        field.use_preconditioner(self.sp)
