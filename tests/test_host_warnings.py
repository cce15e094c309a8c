"""The host-warning filters hide the host's known messages and nothing of ours, only inside their
scope (registry entry ``host_warnings``)."""

import warnings

from sp_plugins.host_warnings import HOST_WARNINGS
from sp_plugins.patches import registry

INDEXING = "Using a non-tuple sequence for multidimensional indexing is deprecated and will be changed in pytorch 2.9"


def _shown(message, category, module, scoped=True):
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        if scoped:
            with registry.scope("host_warnings"):
                warnings.warn_explicit(message, category, f"{module.replace('.', '/')}.py", 1, module=module)
        else:
            warnings.warn_explicit(message, category, f"{module.replace('.', '/')}.py", 1, module=module)
    return len(seen) == 1


def test_host_messages_are_hidden_only_where_the_host_raises_them(monkeypatch):
    monkeypatch.delenv("SP_HOST_WARNINGS", raising=False)
    assert not _shown(INDEXING, UserWarning, "nerfstudio.cameras.cameras")
    assert _shown(INDEXING, UserWarning, "sp_plugins.nerfstudio.seam")  # ours: never hidden
    assert _shown("something else entirely", UserWarning, "nerfstudio.cameras.cameras")
    assert _shown(INDEXING, RuntimeWarning, "nerfstudio.cameras.cameras")  # another category
    assert all(not module.startswith("sp_plugins") for _, _, module in HOST_WARNINGS)


def test_outside_the_scope_every_warning_shows(monkeypatch):
    monkeypatch.delenv("SP_HOST_WARNINGS", raising=False)
    filters = warnings.filters
    _shown(INDEXING, UserWarning, "nerfstudio.cameras.cameras")
    assert warnings.filters is filters
    assert _shown(INDEXING, UserWarning, "nerfstudio.cameras.cameras", scoped=False)


def test_the_environment_switch_keeps_every_warning(monkeypatch):
    monkeypatch.setenv("SP_HOST_WARNINGS", "1")
    assert _shown(INDEXING, UserWarning, "nerfstudio.cameras.cameras")
