"""nerfstudio's SP variants (sp_plugins.nerfstudio.variants), exactly: what each kind's class is made of, the
defaults an SP model config starts with (the position-field preset, a copy per config; the SP model of the
host's own model class), and a name resolved as a fresh ``ns-eval`` process would. Each test names the mutants
it kills (``bench/mutation_study.py`` ``sp_plugins/nerfstudio/variants.py``)."""

from __future__ import annotations

import dataclasses

from nerfstudio.fields.nerfacto_field import NerfactoField
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig

from sp_plugins.adapter import presets
from sp_plugins.adapter.model import SPModelConfig
from sp_plugins.nerfstudio import variants


def test_an_sp_model_config_is_the_hosts_with_sp_and_targets_the_sp_model():
    """An SP model config is a dataclass of the SP config and the host's, with the host's defaults, its own copy of
    ``presets.DEFAULT`` and the SP model of the host's target."""
    cls = variants.variant("ModelConfig", NerfactoModelConfig)
    assert cls.__bases__ == (SPModelConfig, NerfactoModelConfig) and dataclasses.is_dataclass(cls)
    a, b = cls(), cls()
    assert a._target is variants.variant("Model", NerfactoModel) and issubclass(a._target, NerfactoModel)
    assert a.sp == presets.DEFAULT and a.sp is not presets.DEFAULT and a.sp is not b.sp
    host = NerfactoModelConfig()
    for f in dataclasses.fields(host):  # every other default is the host's
        if f.name not in ("_target", "sp"):
            assert getattr(a, f.name) == getattr(host, f.name), f.name
    assert "--pipeline.model.sp" in cls.__doc__ and cls.__doc__.startswith("NerfactoModelConfig with stochastic")


def test_model_and_field_variants_put_their_mixin_first():
    from sp_plugins.nerfstudio.model import SPModel
    from sp_plugins.nerfstudio.seam import SeamField

    model = variants.variant("Model", NerfactoModel)
    field = variants.variant("Field", NerfactoField)
    assert model.__bases__ == (SPModel, NerfactoModel) and model.sp_host_class() is NerfactoModel
    assert field.__bases__ == (SeamField, NerfactoField)
    assert model.__doc__ == "NerfactoModel with stochastic preconditioning."


def test_a_saved_name_resolves_through_the_module():
    """What PyYAML does with a ``config.yml``'s ``!!python/name:`` tag (the module's ``__getattr__``)."""
    name = variants.FACTORY.name("ModelConfig", NerfactoModelConfig)
    assert getattr(variants, name) is variants.variant("ModelConfig", NerfactoModelConfig)
