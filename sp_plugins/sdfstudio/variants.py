"""SP variants of any sdfstudio SDF model and its config, by class path.

Every sdfstudio SDF method (neus, volsdf, unisurf, bakedsdf, neuralangelo, ...) has a model that
is a ``SurfaceModel``: it builds its SDF field from ``config.sdf_field`` (an ``SDFFieldConfig``).
SP enters all of them through the same seam: the field config becomes an
:class:`~sp_plugins.sdfstudio.seam.SeamSDFFieldConfig` and the model config an SP variant of
its own class, made here on demand by a :class:`~sp_plugins.adapter.variants.VariantFactory`
and named after the host class's path, so that a ``config.yml`` naming it loads in a fresh
``ns-eval`` / ``ns-extract-mesh`` / ``eval_setup`` process with no extra step::

    variant("ModelConfig", VolSDFModelConfig)  # SPModelConfig__nerfstudio_dmodels_dvolsdf_dVolSDFModelConfig
    variant("Model", VolSDFModel)              # SPModel__..._dVolSDFModel: (SDFFieldSPModel, VolSDFModel)

A model config variant adds ``sp`` (``--pipeline.model.sp.*``, default
:data:`sp_plugins.adapter.presets.NEUS`) and types ``sdf_field`` as ``SeamSDFFieldConfig`` (so
``--pipeline.model.sdf-field.fd-step`` and ``perturb-sampler-queries`` exist); every other field
and default is the host's. Method configs set the preset per method
(:func:`sp_plugins.sdfstudio.registration.with_sp`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Type

from nerfstudio.models.base_surface_model import SurfaceModel

from sp_plugins.adapter import presets
from sp_plugins.adapter.model import SPModelConfig
from sp_plugins.adapter.variants import VariantFactory, convert, field_default, subclass
from sp_plugins.core import SPConfig
from sp_plugins.sdfstudio.model import SDFFieldSPModel
from sp_plugins.sdfstudio.seam import SeamSDFFieldConfig


def _model_config(host: type, name: str, module: str) -> type:
    host_model = field_default(host, "_target")

    def sdf_field() -> SeamSDFFieldConfig:
        return convert(field_default(host, "sdf_field"), SeamSDFFieldConfig)

    cls = subclass(
        (SPModelConfig, host),
        name,
        module,
        __doc__=f"sdfstudio's {host.__name__} with stochastic preconditioning of its SDF field (``--pipeline.model.sp.*``).",
        __annotations__={"_target": Type, "sdf_field": SeamSDFFieldConfig, "sp": SPConfig},
        _target=field(default_factory=lambda: variant("Model", host_model)),
        sdf_field=field(default_factory=sdf_field),
        sp=field(default_factory=lambda: dataclasses.replace(presets.NEUS)),
    )
    return dataclass(cls)


def _model(host: type, name: str, module: str) -> type:
    if not issubclass(host, SurfaceModel):
        raise ValueError(f"{host.__name__} is not an sdfstudio SurfaceModel: it has no SDF field built from sdf_field")
    return subclass((SDFFieldSPModel, host), name, module, __doc__=f"sdfstudio's {host.__name__} with stochastic preconditioning.")


FACTORY = VariantFactory(__name__, {"ModelConfig": _model_config, "Model": _model})


def variant(kind: str, host: type) -> type:
    """The SP subclass of ``host`` of ``kind`` (``"ModelConfig"`` or ``"Model"``)."""
    return FACTORY.get(kind, host)


def __getattr__(name: str) -> type:  # PEP 562: a saved config.yml names a variant not made yet
    return FACTORY.resolve(name)
