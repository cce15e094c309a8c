"""SP on any sdfstudio SDF method: one conversion of sdfstudio's own method configs.

:func:`with_sp` turns sdfstudio's config of a method (trainer, data, optimizers, schedulers,
field sizes: everything as the host ships it) into ``sp-<method>``: the model config becomes the
SP variant of its own class (:mod:`sp_plugins.sdfstudio.variants`), its ``sdf_field`` an
:class:`~sp_plugins.sdfstudio.sdf_field.SPSDFFieldConfig`, and the trainer gets the optimizer
entry of a learnable alpha grid. It applies to every method whose model is an sdfstudio
``SurfaceModel`` with an ``SDFFieldConfig`` (:func:`refusal` says why any other is refused).
Our four named methods (``method_configs/sdfstudio``) are this conversion with their preset;
:func:`sp_methods` makes it for every registered method.

The paper's SP settings (Ling et al. 2025), schedule ends as fractions of training so that
shortened runs keep their shape (:func:`preset_for`):

- :data:`sp_plugins.adapter.presets.NEUS` (alpha0 0.013, exponential to 0 over the first 20%):
  NeuS, neus-facto and every other SDF method whose host config does not enable Neuralangelo's
  progressive hash encoding (volsdf, unisurf, monosdf, bakedsdf, neus-acc, ...);
- :data:`sp_plugins.adapter.presets.NEURALANGELO` (alpha0 0.03 over the first 30%; or a learnable
  alpha grid initialised to 0.03, Adam lr 1e-3 with ``--pipeline.model.sp.alpha-grid True``) for
  methods whose host config sets ``enable_progressive_hash_encoding=True`` (neuralangelo,
  bakedangelo, neus-facto-angelo). There SP *replaces* coarse-to-fine: all hash levels from step
  0, and the finite-difference step fixed at the value sdfstudio's schedule ends on
  (:data:`FINAL_FD_STEP`). The curvature-loss weight schedule (a loss weight, not a
  representation schedule) is kept.

Alphas are in scene units (sdfstudio normalises scenes to the unit box / sphere).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Dict, Optional, Tuple

from sp_plugins.adapter import presets
from sp_plugins.adapter.variants import class_path, convert, target_class
from sp_plugins.core import SPConfig
from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, alpha_grid_optimizer
from sp_plugins.sdfstudio.registration import MethodSpecification

NEUS_SP = presets.NEUS
NEURALANGELO_SP = presets.NEURALANGELO
PREFIX = "sp-"

FINAL_FD_STEP: Dict[str, float] = {
    "nerfstudio.models.neuralangelo.NeuralangeloModel": 2.0,  # max(1/max_res, d) * 2
    "nerfstudio.models.bakedangelo.BakedAngeloModel": 1.0,  # max(1/(4 max_res), d) * 4
    "nerfstudio.models.neus_facto.NeuSFactoModel": 1.0,  # as bakedangelo (neus-facto-angelo)
}
"""Where sdfstudio's numerical-gradient step schedule ends, times ``1 / sdf_field.max_res``, per
model class (commit 370902a). A model with the schedule that is not listed (nor a subclass of
one) keeps its schedule under SP; only progressive hash encoding is replaced."""

REFUSED_MODELS: Dict[str, str] = {
    "nerfstudio.models.dto.DtoOModel": (
        "its model (DtoOModel) is a nerfacto model: nerfacto's density field renders, and its sdf_field only "
        "builds an occupancy field that guides sampling, so there is no SDF surface for SP to precondition"
    ),
}
"""Host model classes (and subclasses) with an ``sdf_field`` that SP still does not apply to, and why."""


def host_method_config(name: str):
    """A deep copy of sdfstudio's own config of method ``name``."""
    from nerfstudio.configs.method_configs import method_configs

    return copy.deepcopy(method_configs[name])


def refusal(config: Any) -> Optional[str]:
    """Why SP cannot be put on the method of sdfstudio trainer config ``config`` (None when it
    can). Decided from classes only: nothing is built."""
    from nerfstudio.fields.sdf_field import SDFFieldConfig
    from nerfstudio.models.base_surface_model import SurfaceModel

    model_config = getattr(getattr(config, "pipeline", None), "model", None)
    model = target_class(model_config)
    if model is None:
        return "its model config has no model class (_target) to subclass"
    for cls in model.__mro__:
        reason = REFUSED_MODELS.get(class_path(cls))
        if reason:
            return reason
    if not isinstance(getattr(model_config, "sdf_field", None), SDFFieldConfig):
        return (
            f"its model ({model.__name__}) has no SDF field (no sdf_field: SDFFieldConfig in {type(model_config).__name__}); "
            "sdfstudio's SP enters at an SDF field's queries, and this is a radiance-field method"
        )
    if not issubclass(model, SurfaceModel):
        return (
            f"its model ({model.__name__}) is not an sdfstudio SurfaceModel, so its sdf_field is not the field it "
            "renders with; sdfstudio's SP enters at a SurfaceModel's SDF field"
        )
    return None


def replaces_coarse_to_fine(model_config: Any) -> bool:
    """True when the host config enables Neuralangelo's progressive hash encoding."""
    return getattr(model_config, "enable_progressive_hash_encoding", False) is True


def preset_for(model_config: Any) -> SPConfig:
    """The paper's SP settings for a host model config (see the module's docstring)."""
    return dataclasses.replace(NEURALANGELO_SP if replaces_coarse_to_fine(model_config) else NEUS_SP)


def final_fd_step(model: type, max_res: int) -> Optional[float]:
    """Where sdfstudio's numerical-gradient step schedule ends for ``model`` (None: not known)."""
    for cls in model.__mro__:
        factor = FINAL_FD_STEP.get(class_path(cls))
        if factor is not None:
            return factor / max_res
    return None


def sp_model_config(model_config: Any, sp: SPConfig) -> Any:
    """The SP variant of an sdfstudio SDF model config, with ``sp`` (coarse-to-fine replaced where
    the host enables it)."""
    from sp_plugins.sdfstudio.sdf_field import SPSDFFieldConfig
    from sp_plugins.sdfstudio.variants import variant

    model = target_class(model_config)
    assert model is not None
    field_changes: Dict[str, Any] = {}
    model_changes: Dict[str, Any] = {}
    if replaces_coarse_to_fine(model_config):
        model_changes["enable_progressive_hash_encoding"] = False
        fd_step = final_fd_step(model, model_config.sdf_field.max_res)
        if getattr(model_config, "enable_numerical_gradients_schedule", False) and fd_step is not None:
            model_changes["enable_numerical_gradients_schedule"] = False
            field_changes["fd_step"] = fd_step
    sdf_field = convert(model_config.sdf_field, SPSDFFieldConfig, **field_changes)
    return convert(
        model_config,
        variant("ModelConfig", type(model_config)),
        _target=variant("Model", model),
        sdf_field=sdf_field,
        sp=copy.deepcopy(sp),
        **model_changes,
    )


def describe(sp: SPConfig, replaced: bool) -> str:
    what = f"alpha0 {sp.alpha0:g}, to 0 over the first {sp.end:.0%}" if sp.end <= 1 else f"alpha0 {sp.alpha0:g}, to 0 by step {sp.end:g}"
    return ("coarse-to-fine replaced by stochastic preconditioning" if replaced else "+ stochastic preconditioning") + f" ({what})"


def with_sp(config: Any, sp: Optional[SPConfig] = None, *, name: Optional[str] = None, description: Optional[str] = None) -> MethodSpecification:
    """``sp-<method>``: sdfstudio's trainer config ``config`` with SP on its SDF field.

    ``sp`` defaults to :func:`preset_for` the model; ``name`` to ``sp-<method name>``. Raises
    ``ValueError`` naming the reason when SP cannot be put on the method (:func:`refusal`)."""
    config = copy.deepcopy(config)
    base = config.method_name
    if hasattr(config.pipeline.model, "sp"):
        raise ValueError(f"SP cannot be put on {base}: it is already an SP method")
    reason = refusal(config)
    if reason:
        raise ValueError(f"SP cannot be put on {base}: {reason}")
    host_model = config.pipeline.model
    sp = copy.deepcopy(sp) if sp is not None else preset_for(host_model)
    config.pipeline.model = sp_model_config(host_model, sp)
    config.method_name = name or f"{PREFIX}{base}"
    config.optimizers[ALPHA_GRID_GROUP] = alpha_grid_optimizer(sp)
    text = description or f"sdfstudio {base} {describe(sp, replaces_coarse_to_fine(host_model))}."
    return MethodSpecification(config=config, description=text)


def sp_method(base: str, sp: Optional[SPConfig] = None, description: Optional[str] = None) -> MethodSpecification:
    """``sp-<base>`` from sdfstudio's registered method ``base`` (for ``method_configs.sdfstudio``)."""
    return with_sp(host_method_config(base), sp, description=description)


def sp_methods(method_configs: Dict[str, Any], descriptions: Dict[str, str]) -> Tuple[Dict[str, Any], Dict[str, str], Dict[str, str]]:
    """``(configs, descriptions, refused)``, keyed by SP method name (``sp-<method>``): for every
    host method, its SP config or why it is refused. Methods that are already SP methods are skipped."""
    configs: Dict[str, Any] = {}
    texts: Dict[str, str] = {}
    refused: Dict[str, str] = {}
    for method, config in method_configs.items():
        if hasattr(getattr(getattr(config, "pipeline", None), "model", None), "sp"):
            continue  # ours
        name = f"{PREFIX}{method}"
        reason = refusal(config)
        if reason:
            refused[name] = reason
            continue
        host_text = descriptions.get(method, "").rstrip(".")
        spec = with_sp(config, name=name)
        sp = spec.config.pipeline.model.sp
        configs[name] = spec.config
        texts[name] = f"{host_text} ({method}) {describe(sp, replaces_coarse_to_fine(config.pipeline.model))}." if host_text else spec.description
    return configs, texts, refused
