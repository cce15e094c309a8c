"""The models of the sdfstudio adapter: the shared mixin with sdfstudio's few differences.

:class:`SPModel` is :class:`sp_plugins.adapter.model.SPModelBase` (the preconditioner from
``config.sp``, checkpointed, its alpha-grid optimizer group, the schedule callbacks, ``sp_alpha``
in the metrics; the same names as in ``sp_plugins.nerfstudio.model``), except that SP reflects
into the scene contraction's range (the hash grid's domain, where sdfstudio's SDF field is
queried) and the run's length is ``--trainer.max-num-iterations``.

After the first training step with alpha > 0 the model checks, once, that SP moved the positions
its SDF field was queried at (:func:`sp_plugins.sdfstudio.seam.check_reached`), as the nerfstudio
adapter does for its seam.

(LPIPS without downloads is a patch here, :mod:`sp_plugins.patches.sdfstudio_lpips`, because
sdfstudio's own ns-eval builds the same models.)
"""

from __future__ import annotations

from typing import Any, List

from sp_plugins.adapter import model as adapter_model
from sp_plugins.adapter.model import SPModelConfig
from sp_plugins.sdfstudio.seam import CONTRACTED_BOUNDS

__all__ = ["SDFFieldSPModel", "SPModel", "SPModelConfig"]


def unsupported_setting(sp: Any) -> str:
    """Why an SP setting (an ``SPConfig``) cannot act in sdfstudio's SDF methods, or ``""``. Checked by
    ``sp-sdfstudio-train`` before anything is written and again when the model is built."""
    k = sp.num_samples
    if k > 1:  # the contraction moves each query once: K draws would silently train one (issue 44)
        return (
            f"--pipeline.model.sp.num-samples {k} cannot apply to sdfstudio's SDF methods: their seam (the scene "
            "contraction) perturbs each query once and does not average draws; pass --pipeline.model.sp.num-samples 1"
        )
    return ""


class SPModel(adapter_model.SPModelBase):
    """Mixin for an sdfstudio ``Model``; list it before the host model class."""

    steps_flag = "--trainer.max-num-iterations"

    def sp_bounds(self, aabb) -> Any:
        return CONTRACTED_BOUNDS


class SDFFieldSPModel(SPModel):
    """:class:`SPModel` for any sdfstudio ``SurfaceModel``: the preconditioner goes to the SDF
    field ``self.field`` that ``SurfaceModel.populate_modules`` builds from ``config.sdf_field``
    (an :class:`~sp_plugins.sdfstudio.seam.SPSDFFieldConfig` in every SP model config).
    List it before the host model class (the SP model variants of
    :mod:`sp_plugins.sdfstudio.variants` are ``(SDFFieldSPModel, HostModel)``)."""

    def attach_sp(self) -> None:
        from sp_plugins.sdfstudio.seam import SPSDFField

        field = getattr(self, "field", None)
        if not isinstance(field, SPSDFField):
            raise TypeError(
                f"{type(self).__name__}: SP needs the SDF field built from an SPSDFFieldConfig, got "
                f"{type(field).__name__} (the model config's sdf_field must be SPSDFFieldConfig)"
            )
        problem = unsupported_setting(self.sp.config)
        if problem:
            from sp_plugins.adapter.errors import InputError

            raise InputError(problem)
        field.use_preconditioner(self.sp)

    def sp_host_name(self) -> str:
        """The sdfstudio model class this SP variant is built on."""
        return next(c for c in type(self).__mro__ if not c.__module__.startswith("sp_plugins.")).__name__

    def check_sp_reached(self, step: int) -> None:
        """After the first training step with alpha > 0: the field's queries moved (once per run)."""
        if getattr(self, "_sp_reach_checked", False) or not self.sp.active:
            return
        self._sp_reach_checked = True
        from sp_plugins.sdfstudio.seam import check_reached

        check_reached(self.field, self.sp_host_name(), step)  # type: ignore[attr-defined]

    def get_training_callbacks(self, training_callback_attributes) -> List[Any]:
        from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

        callbacks = super().get_training_callbacks(training_callback_attributes)
        reached = TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.check_sp_reached, update_every_num_iters=1)
        return list(callbacks) + [reached]
