"""What the sdfstudio adapter knows about methods: the one file to edit to support or refuse one.

Tables keyed by a host model class's path (``module.QualName``, a string: this module imports no
sdfstudio module) apply to that class and its subclasses, the most derived class a table names
winning (:mod:`sp_plugins.adapter.tables`).

- :data:`REFUSED_MODELS`: models with an ``sdf_field`` that SP still does not apply to, and why.
  A model without an ``SDFFieldConfig``, or not a ``SurfaceModel``, is refused by the rule in
  :func:`sp_plugins.sdfstudio.registration.refusal`; every other SDF method is offered.
- :data:`PRESET`, :data:`COARSE_TO_FINE_PRESET`: the paper's settings; sdfstudio decides by the
  config, not the model class (neus-facto and neus-facto-angelo share ``NeuSFactoModel``).
- :data:`FINAL_FD_STEP`: where sdfstudio's numerical-gradient step schedule ends, for the models
  whose coarse-to-fine SP replaces.

README's sdfstudio method table is generated from this module and the registered methods
(``python -m sp_plugins.method_table --write`` in the sdfstudio environment).
"""

from __future__ import annotations

from typing import Dict

from sp_plugins.adapter import presets
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
