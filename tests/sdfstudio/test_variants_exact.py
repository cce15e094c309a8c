"""sdfstudio's SP variants (sp_plugins.sdfstudio.variants), exactly: an SP model config is the host's with
its SDF field config as the seam's (every host setting kept, a copy per config), the NeuS preset, and the SP
model of the host's model; a model class that is not a SurfaceModel is refused naming it. Each test names the
mutants it kills (``bench/mutation_study.py`` ``sp_plugins/sdfstudio/variants.py``)."""

from __future__ import annotations

import dataclasses

import pytest

pytestmark = pytest.mark.usefixtures("patched")


def test_an_sp_model_config_keeps_the_hosts_settings_with_the_seams_sdf_field():
    """An SP model config keeps the host's settings, with its own seam SDF field config (the host's values) and its
    own copy of ``presets.NEUS``, and targets the SP model."""
    from nerfstudio.models.neus import NeuSModel, NeuSModelConfig

    from sp_plugins.adapter import presets
    from sp_plugins.adapter.model import SPModelConfig
    from sp_plugins.sdfstudio import variants
    from sp_plugins.sdfstudio.model import SDFFieldSPModel
    from sp_plugins.sdfstudio.seam import SeamSDFFieldConfig

    cls = variants.variant("ModelConfig", NeuSModelConfig)
    assert cls.__bases__ == (SPModelConfig, NeuSModelConfig) and dataclasses.is_dataclass(cls)
    a, b, host = cls(), cls(), NeuSModelConfig()
    assert type(a.sdf_field) is SeamSDFFieldConfig and a.sdf_field is not b.sdf_field
    for f in dataclasses.fields(host.sdf_field):
        if f.name != "_target":
            assert getattr(a.sdf_field, f.name) == getattr(host.sdf_field, f.name), f.name
    assert a.sp == presets.NEUS and a.sp is not presets.NEUS and a.sp is not b.sp
    model = variants.variant("Model", NeuSModel)
    assert a._target is model and model.__bases__ == (SDFFieldSPModel, NeuSModel)
    assert getattr(variants, variants.FACTORY.name("ModelConfig", NeuSModelConfig)) is cls


def test_a_model_that_is_not_a_surface_model_is_refused_naming_it():
    """A model that is not an sdfstudio surface model is refused in one line naming it."""
    from nerfstudio.models.nerfacto import NerfactoModel

    from sp_plugins.sdfstudio import variants

    with pytest.raises(ValueError, match=r"^NerfactoModel is not an sdfstudio SurfaceModel: it has no SDF field built from sdf_field$"):
        variants.variant("Model", NerfactoModel)
