"""Guard for patches/nerfstudio_host_fields.py: the host models still build their field from the
module-level names the patch redirects (nerfstudio 1.1.5), and the patch restores them."""

import importlib
import inspect

import pytest

from sp_plugins.patches.nerfstudio_host_fields import HOST_FIELDS, host_builds


@pytest.mark.parametrize("module_name", sorted(HOST_FIELDS))
def test_the_host_model_constructs_the_named_field_class(module_name):
    module = importlib.import_module(module_name)
    name = HOST_FIELDS[module_name]
    model_classes = [c for c in vars(module).values() if inspect.isclass(c) and c.__module__ == module_name and hasattr(c, "populate_modules")]
    sources = [inspect.getsource(c.populate_modules) for c in model_classes]
    assert any(f"{name}(" in src for src in sources), f"{module_name} no longer builds {name} in populate_modules"


def test_host_builds_redirects_and_restores():
    module = importlib.import_module("nerfstudio.models.tensorf")
    host = module.TensoRFField

    class Sub(host):
        pass

    with host_builds("nerfstudio.models.tensorf", Sub):
        assert module.TensoRFField is Sub
        with host_builds("nerfstudio.models.tensorf", Sub):  # nesting is harmless
            assert module.TensoRFField is Sub
    assert module.TensoRFField is host
    with pytest.raises(RuntimeError, match="not supported"):
        with host_builds("nerfstudio.models.tensorf", object):
            pass
    assert module.TensoRFField is host
