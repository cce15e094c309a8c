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
- logs ``sp_alpha`` with the training metrics;
- installs, when it is built (not when nerfstudio discovers our methods), the one-line report
  of :class:`InputError` and the filters for the host's known warnings: only a process that
  trains one of our methods gets them.

:class:`AnyMethodSPModel` is the same for a model we have never seen (``with_sp``): the host's
``populate_modules`` builds its fields as SP variants, and the model refuses, in one line, to
train where SP would reach nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List

import torch
from torch.nn import Parameter

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes

from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.nerfstudio.callbacks import ALPHA_GRID_GROUP, sp_callbacks
from sp_plugins.nerfstudio.errors import InputError, install_input_error_hook
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


def install_process_settings() -> None:
    """What a process that trains or loads one of our methods gets: ``InputError`` as one line
    (exit status 2) and the host's known, non-actionable warnings filtered."""
    from sp_plugins.host_warnings import filter_host_warnings

    install_input_error_hook()
    filter_host_warnings()


class SPModel:
    """Mixin for a nerfstudio ``Model``; list it before the host model class."""

    sp: StochasticPreconditioner

    def populate_modules(self) -> None:
        install_process_settings()
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


class AnyMethodSPModel(SPModel):
    """SP on any nerfstudio model whose fields read ``Frustums.get_positions()``.

    While the host's ``populate_modules`` runs, every module-level ``Field`` class of the
    modules defining the model resolves to its SP variant (a :class:`FrustumSPField` subclass,
    :func:`sp_plugins.patches.nerfstudio_host_fields.model_builds_variants`), so the host builds
    our subclasses with its own arguments. Proposal networks are built that way too but stay
    plain: they are queried through ``density_fn``, not with ``RaySamples``.

    Refused in one line: fields SP cannot reach (none built as a variant), SDF fields (they read
    ``get_start_positions()``, which ignores offsets), Gaussian-blob fields (MipNeRF), a box
    boundary in a contracted scene, and a first training step in which no field was perturbed.
    """

    def populate_modules(self) -> None:
        from sp_plugins.nerfstudio.variants import variant
        from sp_plugins.patches.nerfstudio_host_fields import model_builds_variants

        with model_builds_variants(type(self), lambda host: variant("Field", host)):
            super().populate_modules()

    def sp_host_name(self) -> str:
        host = next(c for c in type(self).__mro__ if not c.__module__.startswith("sp_plugins."))
        return f"{host.__module__}.{host.__qualname__}"

    def sp_fields(self) -> List[torch.nn.Module]:
        from sp_plugins.nerfstudio.frustum_sp import FrustumSPField

        return [m for m in self.modules() if isinstance(m, FrustumSPField)]  # type: ignore[attr-defined]

    def attach_sp(self) -> None:
        from nerfstudio.fields.sdf_field import SDFField

        host, sp = self.sp_host_name(), self.config.sp  # type: ignore[attr-defined]
        for module in self.modules():  # type: ignore[attr-defined]
            if isinstance(module, SDFField):
                raise InputError(
                    f"SP cannot reach {host}: its SDF field reads Frustums.get_start_positions(), which ignores offsets; "
                    "train sp-neus, sp-neus-hashgrid or sp-neuralangelo-lite (nerfstudio) or sp-sdfstudio-train (sdfstudio)"
                )
        fields = self.sp_fields()
        if not fields:
            raise InputError(
                f"SP cannot reach {host}: none of its fields is built from a module-level Field class of the modules that "
                "define the model, so no query would be perturbed; build the field by class name in populate_modules"
            )
        for f in fields:
            if getattr(f, "use_integrated_encoding", False):
                raise InputError(f"SP cannot reach {host}: its field encodes Gaussian blobs (MipNeRF), which refuse "
                                 "Frustums.offsets; train sp-mipnerf")
            if sp.enabled and sp.boundary != "none" and getattr(f, "spatial_distortion", None) is not None:
                raise InputError(
                    f"--pipeline.model.sp.boundary {sp.boundary} needs a bounded scene, but {type(f).__bases__[-1].__name__} "
                    "contracts space (scene contraction); pass --pipeline.model.sp.boundary none"
                )
            f.use_preconditioner(self.sp)

    def perturbed_calls(self) -> int:
        return sum(f.sp_handle.perturbed_calls for f in self.sp_fields() if f.sp_handle is not None)

    def check_sp_reached(self, step: int) -> None:
        """After the first training step with alpha > 0: some field must have been perturbed."""
        if getattr(self, "_sp_reach_checked", False) or not self.sp.active:
            return
        self._sp_reach_checked = True
        if self.perturbed_calls() == 0:
            raise InputError(
                f"SP reached no field of {self.sp_host_name()} in training step {step}: no field was called with "
                "RaySamples (fields queried only through positions or density_fn stay plain); SP does not apply to this method"
            )

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        from nerfstudio.engine.callbacks import TrainingCallbackLocation

        callbacks = super().get_training_callbacks(training_callback_attributes)
        check = TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.check_sp_reached, update_every_num_iters=1)
        return callbacks + [check]
