"""The models of the nerfstudio adapter: the shared mixin with nerfstudio's few differences.

:class:`SPModel` is :class:`sp_plugins.adapter.model.SPModel` (the preconditioner from
``config.sp`` over the scene box, checkpointed, its alpha-grid optimizer group, the schedule
callbacks, ``sp_alpha`` in the metrics) plus, for nerfstudio 1.x:

- LPIPS built without downloads and kept out of the state dict (every nerfstudio model builds
  torchmetrics' LPIPS, which fetches AlexNet weights);
- options that only act through SP refused on a baseline (``sp.enabled False``);
- when it is built (not when nerfstudio discovers our methods), the one-line report of
  :class:`InputError` and the filters for the host's known warnings: only a process that trains
  or loads one of our methods gets them.

:class:`AnyMethodSPModel` is the same for a model we have never seen (``with_sp``): the host's
``populate_modules`` builds its fields as SP variants, and the model refuses, in one line, to
train where SP would reach nothing.
"""

from __future__ import annotations

from typing import Callable, Dict, List

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes

from sp_plugins.adapter import model as adapter_model
from sp_plugins.adapter.model import SPModelConfig
from sp_plugins.adapter.variants import class_path
from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.adapter.checks import check_known_settings
from sp_plugins.adapter.errors import InputError, install_input_error_hook
from sp_plugins.nerfstudio.host.lpips import detach_lpips, drop_missing_lpips, offline_lpips

__all__ = ["AnyMethodSPModel", "SPModel", "SPModelConfig", "install_process_settings", "refuse_inert_options"]


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


def install_process_settings() -> None:
    """What a process that trains or loads one of our methods gets: ``InputError`` as one line
    (exit status 2) and the host's known, non-actionable warnings filtered."""
    from sp_plugins.host_warnings import filter_host_warnings

    install_input_error_hook()
    filter_host_warnings()


def check_finite_losses(losses: Dict[str, torch.Tensor], step: int, groups: Callable[[], List[str]]) -> None:
    """Stop a run whose loss turned NaN or infinite, naming the step and what to try: training on
    would only write NaN checkpoints. (One device sync per step for the check.)"""
    total = sum(v.detach().float().sum() for v in losses.values())
    if bool(torch.isfinite(total)):
        return
    bad = [f"{name}={float(v.detach().float().sum()):g}" for name, v in losses.items() if not bool(torch.isfinite(v.detach()).all())]
    flags = ", ".join(f"--optimizers.{g.replace('_', '-')}.optimizer.lr" for g in groups()[:3]) or "--optimizers.<group>.optimizer.lr"
    raise InputError(
        f"training step {step}: the loss became {' and '.join(bad) or 'NaN'}; the run diverged and stopped (nothing from this step "
        f"was saved): lower the learning rate ({flags}, e.g. 10x smaller) or resume from an earlier checkpoint with --load-dir"
    )


class SPModel(adapter_model.SPModel):
    """Mixin for a nerfstudio ``Model``; list it before the host model class."""

    def populate_modules(self) -> None:
        install_process_settings()
        check_known_settings(self.config, "pipeline.model")  # type: ignore[attr-defined]  (a config.yml of another version)
        super().populate_modules()

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        losses = super().get_loss_dict(outputs, batch, metrics_dict)  # type: ignore[misc]
        if self.training:  # type: ignore[attr-defined]
            check_finite_losses(losses, int(getattr(self.sp, "_step", 0)), self._lr_groups)
        return losses

    def _lr_groups(self) -> List[str]:
        from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP

        return [g for g in self.get_param_groups() if g != ALPHA_GRID_GROUP]  # type: ignore[attr-defined]

    def build_preconditioner(self) -> StochasticPreconditioner:
        refuse_inert_options(self.config.sp)  # type: ignore[attr-defined]
        return super().build_preconditioner()

    def populate_host_modules(self) -> None:
        with offline_lpips():
            super().populate_host_modules()
        detach_lpips(self)  # type: ignore[arg-type]

    def get_image_metrics_and_images(self, outputs, batch):
        metrics, images = super().get_image_metrics_and_images(outputs, batch)  # type: ignore[misc]
        return drop_missing_lpips(self, metrics), images  # type: ignore[arg-type]


ALPHA_GRID_UNREACHABLE = {
    "nerfstudio.models.tensorf.TensoRFModel": (
        "TensoRF", "nerfstudio's TensoRF encoding detaches its sample positions, so no gradient reaches the alpha grid"
    ),
}
"""Host models whose fields detach the positions they read: a learnable alpha grid cannot learn."""


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
        return class_path(next(c for c in type(self).__mro__ if not c.__module__.startswith("sp_plugins.")))

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
        if sp.enabled and sp.alpha_grid:
            for cls in type(self).__mro__:
                unreachable = ALPHA_GRID_UNREACHABLE.get(class_path(cls))
                if unreachable:
                    raise InputError(f"--pipeline.model.sp.alpha-grid True cannot learn on {unreachable[0]}: {unreachable[1]}; "
                                     "use a global alpha (the default)")
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
                way_out = " (or --pipeline.model.disable-scene-contraction True)" if hasattr(self.config, "disable_scene_contraction") else ""  # type: ignore[attr-defined]
                raise InputError(
                    f"--pipeline.model.sp.boundary {sp.boundary} needs a bounded scene, but {type(f).__bases__[-1].__name__} "
                    f"contracts space (scene contraction is on); pass --pipeline.model.sp.boundary none{way_out}"
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
        grid = self.sp.alpha_grid
        if grid is not None and all(p.grad is None or not bool(p.grad.any()) for p in grid.parameters()):
            raise InputError(
                f"--pipeline.model.sp.alpha-grid True cannot learn on {self.sp_host_name()}: no gradient reached the alpha "
                "grid in the first training step (the field detaches the positions it reads); use a global alpha (the default)"
            )

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        from nerfstudio.engine.callbacks import TrainingCallbackLocation

        callbacks = super().get_training_callbacks(training_callback_attributes)
        check = TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.check_sp_reached, update_every_num_iters=1)
        return callbacks + [check]
