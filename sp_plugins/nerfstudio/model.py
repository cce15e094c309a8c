"""The model of the nerfstudio adapter: one mixin for our methods and for ``with_sp`` on any method.

:class:`SPModel` is :class:`sp_plugins.adapter.model.SPModelBase` (the preconditioner from ``config.sp``
over the scene box, checkpointed, its alpha-grid optimizer group, the schedule callbacks,
``sp_alpha`` in the metrics) plus, for nerfstudio 1.x:

- the seam (:mod:`sp_plugins.nerfstudio.seam`) attached to the fields the host's ``populate_modules``
  built, whatever way it built them; the submodules of ``table.PLAIN_FIELDS`` stay plain;
- refusals in one line where SP cannot act: no field called with ``RaySamples``, a field that reads
  positions some other way (checked after the first step with alpha > 0), a box boundary in a
  contracted scene, an alpha grid no gradient reaches;
- the host's build scoped with what it needs offline or without CUDA: LPIPS without downloads
  (and out of the state dict), nerfstudio's ``SDFField`` on our torch hash grid without tcnn;
- options that only act through SP refused on a baseline (``sp.enabled False``);
- when it is built (not when nerfstudio discovers our methods), the one-line report of
  :class:`InputError` and the filters for the host's known warnings.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation

from sp_plugins.adapter import model as adapter_model
from sp_plugins.adapter.model import SPModelConfig
from sp_plugins.adapter.variants import class_path, target_class
from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, RunLength, Where, run_length
from sp_plugins.adapter.checks import check_known_settings
from sp_plugins.adapter.errors import InputError, build_failure
from sp_plugins.adapter.tables import lookup, merged
from sp_plugins.nerfstudio import table
from sp_plugins.nerfstudio.host import HOST
from sp_plugins.nerfstudio.components.colliders import GRAZING_RAYS_HINT, unbounded_surface_rays
from sp_plugins.nerfstudio.components.viewer_panel import SPPanel, update_callback
from sp_plugins.nerfstudio.components.lpips import detach_lpips, drop_missing_lpips, offline_lpips
from sp_plugins.nerfstudio.divergence import NonFiniteWatch, divergence_callback
from sp_plugins.nerfstudio import variants
from sp_plugins.nerfstudio.seam import ALPHA_GRID_OUTPUT, attach_seam, check_reached, seam_fields
from sp_plugins.patches import registry
from sp_plugins.patches.torch_deterministic import mode

__all__ = ["SPModel", "SPModelConfig", "hold_under_host_command", "host_command", "install_process_settings", "refuse_inert_options",
           "refuse_unreachable_settings"]


TORCH_HASH_ENCODING_COST = "about 8% per step at 2 threads (bench/speed/deterministic_cost.py)"


def uses_torch_hash_encoding(model: torch.nn.Module) -> bool:
    """Whether ``model`` holds nerfstudio's torch ``HashEncoding`` (the one whose backward needs the ordered kernel)."""
    from nerfstudio.field_components.encodings import HashEncoding

    return any(isinstance(m, HashEncoding) and getattr(m, "tcnn_encoding", None) is None for m in model.modules())


def hold_deterministic_kernels(model: torch.nn.Module) -> bool:
    """Under ``ns-*`` or ``sp-train`` on a run of ours: torch's deterministic kernels while ``model`` exists
    (``patches/torch_deterministic.py``), where they are needed and cost nothing measurable. ``SP_DETERMINISTIC=auto``
    (the default) leaves them off on one thread (every sum has one order there) and for a model with nerfstudio's
    torch ``HashEncoding`` on several threads, where they cost about 8% per step (it says so once);
    ``SP_DETERMINISTIC=1`` turns them on everywhere. Returns whether held."""
    if not (host_command() or registry.our_console_command() == "sp-train"):
        return False
    try:
        auto = mode() == "auto"
    except ValueError as err:
        raise InputError(str(err)) from None
    if auto and torch.get_num_threads() == 1:
        return False  # one thread: every sum has one order already
    if auto and uses_torch_hash_encoding(model):
        logging.getLogger(__name__).warning(
            "nerfstudio's torch hash encoding on %d threads: runs are not bit-repeatable (its backward sums colliding "
            "rows in thread order); SP_DETERMINISTIC=1 makes them repeatable at %s, or train on one thread "
            "(OMP_NUM_THREADS=1)", torch.get_num_threads(), TORCH_HASH_ENCODING_COST)
        return False
    registry.hold("torch_deterministic", model)
    return True


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


def host_command() -> bool:
    """True when this process is one of the host's console commands (``ns-*``): a command working on
    a run of ours. A Python session, a notebook or a test building our model is not one, and gets
    nothing installed."""
    return Path(sys.argv[0] if sys.argv else "").name.startswith("ns-")


def hold_under_host_command(owner: object) -> None:
    """Under a host command on a run of ours (:func:`host_command`): the one-line hook and the warning
    filters while ``owner`` (our model or data manager) exists; elsewhere nothing."""
    if host_command():
        install_process_settings(owner, run=True)


def install_process_settings(owner: object = None, *, run: bool = False) -> None:
    """What a process that trains or loads one of our methods gets.

    - Without ``owner``: our own console command (``sp-train``) owns the process: failures our
      checks describe print as one line (exit status 2) and the host's known, non-actionable
      warnings are filtered, until it ends (registry entries ``input_error_hook``, ``host_warnings``).
    - With ``owner`` and ``run``: the host's command works on a run of ours (``ns-train``'s checked
      run config, :func:`sp_plugins.nerfstudio.components.trainer.preflight`; our model or data manager
      under ``ns-eval`` / ``ns-render`` / ``ns-export`` / ``ns-viewer``, :func:`host_command`): both are
      held while ``owner`` exists (a damaged checkpoint or a full disk is one line too).
    - With ``owner`` alone: only the one-line hook, held while ``owner`` exists.

    Building one of our models in a Python session, a notebook or a test installs nothing;
    there an ``InputError`` holds the hook itself while it exists (:class:`~sp_plugins.adapter.errors.InputError`)."""
    if owner is None:
        for name in ("input_error_hook", "host_warnings"):
            registry.install_for_process(name, command="sp-train")
        return
    for name in ("input_error_hook", "host_warnings") if run else ("input_error_hook",):
        registry.hold(name, owner)


def refuse_unreachable_settings(model_config: object) -> None:
    """SP settings that cannot act on this model, as far as its config tells: an option that acts
    only through SP on a baseline, an alpha grid on a field that detaches positions, a box
    boundary on a field that contracts space. Run before ``ns-train`` writes the run folder
    (:func:`sp_plugins.nerfstudio.components.trainer.preflight`) and again when the model is built."""
    sp = getattr(model_config, "sp", None)
    if not isinstance(sp, SPConfig):
        return
    refuse_inert_options(sp)
    if not sp.enabled:
        return
    host = target_class(model_config)
    unreachable = lookup(table.ALPHA_GRID_UNREACHABLE, host)
    if sp.alpha_grid and unreachable:
        name, why = unreachable[1]
        raise InputError(f"--pipeline.model.sp.alpha-grid True cannot learn on {name}: {why}; use a global alpha (the default)")
    contracted = lookup(table.CONTRACTED_MODELS, host)
    if sp.boundary != "none" and contracted:
        path, flag = contracted
        if flag is None or not getattr(model_config, flag, False):
            way_out = f" (or --pipeline.model.{flag.replace('_', '-')} True)" if flag else ""
            raise InputError(
                f"--pipeline.model.sp.boundary {sp.boundary} needs a bounded scene, but {path.rsplit('.', 1)[-1]} contracts "
                f"space (scene contraction is on); pass --pipeline.model.sp.boundary none{way_out}"
            )


class SPModel(adapter_model.SPModelBase):
    """Mixin for a nerfstudio ``Model``; list it before the host model class."""

    steps_flag = HOST.flags.steps
    sp_flag = HOST.flags.sp

    def populate_modules(self) -> None:
        hold_under_host_command(self)  # ns-eval, ns-render, ns-export, ns-viewer on our run: its failures as one line
        check_known_settings(self.config, "pipeline.model")  # type: ignore[attr-defined]  (a config.yml of another version)
        self._sp_watch = NonFiniteWatch()
        super().populate_modules()

    def populate_host_modules(self) -> None:
        try:
            with offline_lpips(), registry.scope("nerfstudio_sdf_field"):  # for this build only
                super().populate_host_modules()
        except OSError as exc:  # a plugin that downloads weights while it builds, run offline: one line
            line = build_failure(exc, self.sp_host_class(), "its model was built (populate_modules), before any training step")
            if line is None:
                raise
            raise InputError(line) from exc
        detach_lpips(self)  # type: ignore[arg-type]

    def build_preconditioner(self) -> StochasticPreconditioner:
        refuse_unreachable_settings(self.config)  # type: ignore[attr-defined]  (runs not started by ns-train)
        return super().build_preconditioner()

    def attach_sp(self) -> None:
        hold_deterministic_kernels(self)  # the host's modules are built: what they need is known
        self._attach_seam()
        if self.sp.config.enabled:  # the viewer's SP panel (a baseline shows none)
            self.stochastic_preconditioning = SPPanel(self.sp)

    def get_outputs(self, ray_bundle) -> Dict[str, torch.Tensor]:
        """The host's outputs, plus, in a render of a model with a learnable alpha grid, the grid's
        expected value along each ray (``sp_alpha_grid``: the viewer's "Output type", ``ns-render
        --rendered-output-names sp_alpha_grid``)."""
        outputs = super().get_outputs(ray_bundle)  # type: ignore[misc]
        if self.sp.alpha_grid is not None and not self.training:  # type: ignore[attr-defined]
            for _, field in seam_fields(self):  # type: ignore[arg-type]
                handle = field.sp_handle
                if handle is not None and handle.alpha_render is not None:  # the last field called: the one rendered
                    outputs[ALPHA_GRID_OUTPUT], handle.alpha_render = handle.alpha_render, None
        return outputs

    def get_outputs_for_camera(self, camera, obb_box=None) -> Dict[str, torch.Tensor]:
        """The host's render, or, in the viewer's render thread with the panel set to the field SP
        trains, the mean of perturbed renders (:meth:`SPPanel.render`); evaluation is the host's."""
        host_render = super().get_outputs_for_camera  # type: ignore[misc]
        panel = getattr(self, "stochastic_preconditioning", None)
        if panel is None:
            return host_render(camera, obb_box=obb_box)
        return panel.render(lambda: host_render(camera, obb_box=obb_box))

    # -- what SPModelBase asks of a host -------------------------------------------------------------
    @classmethod
    def sp_preset(cls, model_config: Any) -> SPConfig:
        return table.preset_for(model_config)

    def sp_run_length(self, attributes: Any) -> RunLength:
        """nerfstudio 1.x keeps the length on ``attributes.trainer.config`` and the start step on the
        trainer (``_start_step``: a resumed run's checkpoint step + 1)."""
        trainer = getattr(attributes, "trainer", None)
        return run_length(getattr(getattr(trainer, "config", None), "max_num_iterations", None), getattr(trainer, "_start_step", None))

    def sp_scene_aabb(self) -> torch.Tensor:
        return self.scene_box.aabb  # type: ignore[attr-defined]

    def sp_training_callback(self, where: Where, func: Callable[[int], None]) -> TrainingCallback:
        at = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION if where == "before" else TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        return TrainingCallback([at], func, update_every_num_iters=1)

    # -- the seam --------------------------------------------------------------------------------
    def sp_plain_fields(self) -> Dict[str, str]:
        return merged(table.PLAIN_FIELDS, type(self))

    def _attach_seam(self) -> None:
        host = class_path(self.sp_host_class())
        if not attach_seam(self, self.sp, self.sp_plain_fields()):  # type: ignore[arg-type]
            raise InputError(
                f"SP cannot reach {host}: none of its modules is a nerfstudio Field or takes ray_samples in forward, so "
                "no query would be perturbed"
            )

    def check_sp_reached(self, step: int) -> None:
        """After the first training step with alpha > 0: the fields read the moved positions, and a
        learnable alpha grid got a gradient."""
        host = class_path(self.sp_host_class())
        check_reached(self, host, step, self.sp.config.boundary)  # type: ignore[arg-type]
        grid = self.sp.alpha_grid
        if grid is not None and all(p.grad is None or not bool(p.grad.any()) for p in grid.parameters()):
            raise InputError(
                f"--pipeline.model.sp.alpha-grid True cannot learn on {host}: no gradient reached the alpha "
                "grid in the first training step (the field detaches the positions it reads); use a global alpha (the default)"
            )

    # -- training -------------------------------------------------------------------------------
    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        callbacks.append(divergence_callback(self._sp_watch, self._lr_groups, training_callback_attributes,
                                             self._divergence_hint))
        panel = getattr(self, "stochastic_preconditioning", None)
        if panel is not None:
            callbacks.append(self.sp_training_callback("after", update_callback(panel)))
        return callbacks

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        losses = super().get_loss_dict(outputs, batch, metrics_dict)  # type: ignore[misc]
        if self.training:  # type: ignore[attr-defined]
            self._sp_watch.update(losses, int(getattr(self.sp, "_step", 0)))
        return losses

    def _divergence_hint(self) -> Optional[str]:
        """A surface model that kept nerfstudio's box collider (``sp-train neus``, a plugin's NeuS): its grazing
        rays can make the background NaN whatever the learning rate (components/colliders.py)."""
        return GRAZING_RAYS_HINT if unbounded_surface_rays(self) else None

    def _lr_groups(self) -> List[str]:
        return [g for g in self.get_param_groups() if g != ALPHA_GRID_GROUP]  # type: ignore[attr-defined]

    def get_image_metrics_and_images(self, outputs, batch):
        metrics, images = super().get_image_metrics_and_images(outputs, batch)  # type: ignore[misc]
        return drop_missing_lpips(self, metrics), images  # type: ignore[arg-type]


variants.FACTORY.register("Model", SPModel)
