"""The models of the sdfstudio adapter: the shared mixin with sdfstudio's few differences.

:class:`SPModel` is :class:`sp_plugins.adapter.model.SPModelBase` (the preconditioner from
``config.sp``, checkpointed, its alpha-grid optimizer group, the schedule callbacks, ``sp_alpha``
in the metrics; the same names as in ``sp_plugins.nerfstudio.model``), except that SP reflects
into the scene contraction's range (the hash grid's domain, where sdfstudio's SDF field is
queried) and the run's length is ``--trainer.max-num-iterations``.

After the first training step with alpha > 0 the base checks, once, that SP reached the SDF field
(:meth:`SDFFieldSPModel.check_sp_reached`: :func:`sp_plugins.sdfstudio.seam.check_reached`), as it
does for the nerfstudio adapter's seam.

(LPIPS without downloads is a patch here, :mod:`sp_plugins.patches.sdfstudio_lpips`, because
sdfstudio's own ns-eval builds the same models.)
"""

from __future__ import annotations

from typing import Any, Callable

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

from sp_plugins.adapter import model as adapter_model
from sp_plugins.adapter.callbacks import RunLength, Where, run_length
from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.model import SPModelConfig
from sp_plugins.core import SPConfig
from sp_plugins.sdfstudio.host import HOST
from sp_plugins.sdfstudio.table import preset_for
from sp_plugins.sdfstudio.seam import CONTRACTED_BOUNDS, SeamSDFField, check_reached

__all__ = ["SDFFieldSPModel", "SPModel", "SPModelConfig"]


def unsupported_setting(sp: Any) -> str:
    """Why an SP setting (an ``SPConfig``) cannot act in sdfstudio's SDF methods, or ``""``. Checked by
    ``sp-sdfstudio-train`` before anything is written and again when the model is built."""
    k = sp.num_samples
    if k > 1:  # the contraction moves each query once: K draws would silently train one
        return (
            f"--pipeline.model.sp.num-samples {k} cannot apply to sdfstudio's SDF methods: their seam (the scene "
            "contraction) perturbs each query once and does not average draws; pass --pipeline.model.sp.num-samples 1"
        )
    return ""


class SPModel(adapter_model.SPModelBase):
    """Mixin for an sdfstudio ``Model``; list it before the host model class."""

    steps_flag = HOST.flags.steps
    sp_flag = HOST.flags.sp

    def sp_bounds(self, aabb) -> Any:
        return CONTRACTED_BOUNDS

    @classmethod
    def sp_preset(cls, model_config: Any) -> SPConfig:
        return preset_for(model_config)

    def sp_scene_aabb(self) -> torch.Tensor:
        return self.scene_box.aabb  # type: ignore[attr-defined]

    def sp_run_length(self, attributes: Any) -> RunLength:
        """sdfstudio keeps the length on ``attributes.config`` and passes no trainer, so no start
        step: SP stays at the step its checkpoint loaded."""
        return run_length(getattr(getattr(attributes, "config", None), "max_num_iterations", None))

    def sp_training_callback(self, where: Where, func: Callable[[int], None]) -> TrainingCallback:
        at = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION if where == "before" else TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        return TrainingCallback([at], func, update_every_num_iters=1)


class SDFFieldSPModel(SPModel):
    """:class:`SPModel` for any sdfstudio ``SurfaceModel``: the preconditioner goes to the SDF
    field ``self.field`` that ``SurfaceModel.populate_modules`` builds from ``config.sdf_field``
    (an :class:`~sp_plugins.sdfstudio.seam.SeamSDFFieldConfig` in every SP model config).
    List it before the host model class (the SP model variants of
    :mod:`sp_plugins.sdfstudio.variants` are ``(SDFFieldSPModel, HostModel)``)."""

    def attach_sp(self) -> None:
        field = getattr(self, "field", None)
        if not isinstance(field, SeamSDFField):
            raise TypeError(
                f"{type(self).__name__}: SP needs the SDF field built from an SeamSDFFieldConfig, got "
                f"{type(field).__name__} (the model config's sdf_field must be SeamSDFFieldConfig)"
            )
        problem = unsupported_setting(self.sp.config)
        if problem:
            raise InputError(problem)
        field.use_preconditioner(self.sp)

    def check_sp_reached(self, step: int) -> None:
        """After the first training step with alpha > 0: the SDF field's queries moved."""
        check_reached(self, self.sp_host_class().__name__, step)
