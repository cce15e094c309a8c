"""SP variants of any nerfstudio model, model config and field, by class path.

``with_sp`` (:mod:`sp_plugins.nerfstudio.registration`) wraps methods whose classes we have never
seen; their SP subclasses are made here on demand and named after the host class's path, so a
``config.yml`` that names them loads in a fresh ``ns-eval`` / ``ns-render`` / ``ns-export`` /
``ns-viewer`` process with no extra step (see :mod:`sp_plugins.adapter.variants`)::

    variant("ModelConfig", NerfactoModelConfig)  # SPModelConfig__nerfstudio_dmodels_dnerfacto_dNerfactoModelConfig
    variant("Model", NerfactoModel)              # SPModel__...
    variant("Field", NerfactoField)              # SPField__..., the class a built field instance is swapped to

A leaf: the mixins that go first among the bases (:class:`sp_plugins.nerfstudio.model.SPModel`,
:class:`sp_plugins.nerfstudio.seam.SeamField`) register with :data:`FACTORY` when their modules are
imported.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Type

from sp_plugins.adapter import presets
from sp_plugins.adapter.model import SPModelConfig
from sp_plugins.adapter.variants import VariantFactory, field_default, subclass
from sp_plugins.core import SPConfig


def _model_config(host: type, name: str, module: str) -> type:
    host_model = field_default(host, "_target")
    cls = subclass(
        (SPModelConfig, host),
        name,
        module,
        __doc__=f"{host.__name__} with stochastic preconditioning (``--pipeline.model.sp.*``).",
        __annotations__={"_target": Type, "sp": SPConfig},
        _target=field(default_factory=lambda: variant("Model", host_model)),
        sp=field(default_factory=lambda: dataclasses.replace(presets.DEFAULT)),
    )
    return dataclass(cls)


def _model(host: type, name: str, module: str) -> type:
    return subclass((FACTORY.mixin("Model"), host), name, module, __doc__=f"{host.__name__} with stochastic preconditioning.")


def _field(host: type, name: str, module: str) -> type:
    return subclass((FACTORY.mixin("Field"), host), name, module, __doc__=f"{host.__name__} carrying the SP seam (moved RaySamples).")


FACTORY = VariantFactory(__name__, {"ModelConfig": _model_config, "Model": _model, "Field": _field},
                         providers={"Model": "sp_plugins.nerfstudio.model", "Field": "sp_plugins.nerfstudio.seam"})


def variant(kind: str, host: type) -> type:
    """The SP subclass of ``host`` of ``kind`` (``"ModelConfig"``, ``"Model"``, ``"Field"``)."""
    return FACTORY.get(kind, host)


def __getattr__(name: str) -> type:  # PEP 562: a saved config.yml names a variant not made yet
    return FACTORY.resolve(name)
