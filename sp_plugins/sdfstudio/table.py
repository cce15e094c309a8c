"""What the sdfstudio adapter knows about methods: the one file to edit to support or refuse one.

Tables keyed by a host model class's path (``module.QualName``, a string: this module imports no
sdfstudio module) apply to that class and its subclasses, the most derived class a table names
winning (:mod:`sp_plugins.adapter.tables`).

- :data:`REFUSED_MODELS`: models with an ``sdf_field`` that SP still does not apply to, and why.
  A model without an ``SDFFieldConfig``, or not a ``SurfaceModel``, is refused by the rule in
  :func:`refusal`; every other SDF method is offered.
- :data:`PRESET`, :data:`COARSE_TO_FINE_PRESET`: the paper's settings; sdfstudio decides by the
  config, not the model class (neus-facto and neus-facto-angelo share ``NeuSFactoModel``).
- :data:`FINAL_FD_STEP`: where sdfstudio's numerical-gradient step schedule ends, for the models
  whose coarse-to-fine SP replaces.
- :data:`OUR_METHODS`: the methods of our entry-point group (``sp_plugins.sdfstudio_methods``).
- :data:`READ_POINTS`: where a field's samplers query their ray samples (the seam perturbs what the SDF
  field's contraction returns; its sampler queries, ``get_sdf`` / ``get_density``, read these positions).

:func:`preset_for` and :func:`refusal` read these tables; everything else asks them.

README's sdfstudio method table is generated from this module and the registered methods
(``python -m sp_plugins.method_table --write`` in the sdfstudio environment).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, Optional, Tuple

from sp_plugins.adapter import presets
from sp_plugins.adapter.variants import table_refusal
from sp_plugins.core import SPConfig

REFUSED_MODELS: Dict[str, str] = {
    "nerfstudio.models.dto.DtoOModel": (
        "its model (DtoOModel) is a nerfacto model: nerfacto's density field renders, and its sdf_field only "
        "builds an occupancy field that guides sampling, so there is no SDF surface for SP to precondition"
    ),
}
"""Host model classes with an ``sdf_field`` that SP still does not apply to, and why."""

PRESET: SPConfig = presets.NEUS
"""Every SDF method's SP settings, unless :data:`COARSE_TO_FINE_PRESET` applies."""

COARSE_TO_FINE_PRESET: SPConfig = presets.NEURALANGELO
"""Where the host config enables Neuralangelo's progressive hash encoding (neuralangelo, bakedangelo,
neus-facto-angelo): SP then replaces coarse-to-fine."""

FINAL_FD_STEP: Dict[str, float] = {
    "nerfstudio.models.neuralangelo.NeuralangeloModel": 2.0,  # max(1/max_res, d) * 2
    "nerfstudio.models.bakedangelo.BakedAngeloModel": 1.0,  # max(1/(4 max_res), d) * 4
    "nerfstudio.models.neus_facto.NeuSFactoModel": 1.0,  # as bakedangelo (neus-facto-angelo)
}
"""Where sdfstudio's numerical-gradient step schedule ends, times ``1 / sdf_field.max_res``, per
model class (commit 370902a). A model with the schedule that is not listed (nor a subclass of
one) keeps its schedule under SP; only progressive hash encoding is replaced."""

READ_POINTS: Dict[str, str] = {
    "nerfstudio.fields.sdf_field.SDFField": "get_start_positions",
}
"""Host field classes (and subclasses) and the ``Frustums`` accessor their queries read: sdfstudio's SDF field
queries the bins' starts, in ``get_outputs`` and in its samplers' ``get_sdf`` / ``get_density`` alike (the same
entry as the nerfstudio host's ``READ_POINTS``; sdfstudio's package is also named ``nerfstudio``)."""

OUR_METHODS: Tuple[str, ...] = ("sp-neus", "sp-neus-facto", "sp-neuralangelo", "sp-bakedangelo")
"""The methods of our entry-point group: fixed names and presets, next to the generic ``sp-<method>``."""


def replaces_coarse_to_fine(model_config: Any) -> bool:
    """True when the host config enables Neuralangelo's progressive hash encoding."""
    return getattr(model_config, "enable_progressive_hash_encoding", False) is True


def preset_for(model_config: Any) -> SPConfig:
    """A copy of the paper's SP settings (Ling et al. 2025) for an sdfstudio host model config.

    Decided by the config, not the model class as in nerfstudio (neus-facto and neus-facto-angelo
    share ``NeuSFactoModel``): :data:`COARSE_TO_FINE_PRESET` where the host enables Neuralangelo's
    progressive hash encoding (SP then replaces coarse-to-fine), :data:`PRESET` otherwise."""
    return dataclasses.replace(COARSE_TO_FINE_PRESET if replaces_coarse_to_fine(model_config) else PRESET)


def refusal(config: Any) -> Optional[str]:
    """Why SP cannot be put on the method of sdfstudio trainer config ``config`` (None when it
    can): :data:`REFUSED_MODELS`, then the rule (an ``SDFFieldConfig`` on a ``SurfaceModel``).
    Decided from classes only: nothing is built."""
    from nerfstudio.fields.sdf_field import SDFFieldConfig
    from nerfstudio.models.base_surface_model import SurfaceModel

    model, reason = table_refusal(getattr(getattr(config, "pipeline", None), "model", None), REFUSED_MODELS)
    model_config = config.pipeline.model if model is not None else None
    if reason or model is None or hasattr(model_config, "sp"):
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
