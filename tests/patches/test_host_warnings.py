"""The host-warning filters hide the host's known messages and nothing of ours, only inside their
scope (registry entry ``host_warnings``).

Another test in the same worker may have left one of our models alive (a reference cycle not yet
collected), which holds the filters (``registry.hold``), and pytest's per-test ``catch_warnings``
may have dropped that hold's filters: the checks below hold in every case, so they do not depend on
which tests ran before."""

import gc
import warnings

from sp_plugins.patches.host_warnings import HOST_WARNINGS, host_warnings_shown
from sp_plugins.patches import registry

INDEXING = "Using a non-tuple sequence for multidimensional indexing is deprecated and will be changed in pytorch 2.9"


def _shown(message, category, module, scoped=True):
    """Whether one warning reaches the user. "always" goes *last*, so a filter in force (ours, from
    the scope or from a hold) decides first; without one, the warning shows every time."""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", append=True)
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
    gc.collect()
    filters, before = warnings.filters, list(warnings.filters)
    with registry.scope("host_warnings"):
        pass
    assert warnings.filters is filters and warnings.filters == before  # the same list, the same entries
    held = host_warnings_shown()  # (only by a live model of an earlier test, inside this test's filters)
    assert _shown(INDEXING, UserWarning, "nerfstudio.cameras.cameras", scoped=False) is not held


def test_a_hold_whose_filters_a_warnings_block_dropped_is_entered_again(monkeypatch):
    """pytest (and any ``catch_warnings`` block) restores the list it saved: the filters a hold added
    inside it are gone while the registry still counts the hold; the next scope puts them back."""
    monkeypatch.delenv("SP_HOST_WARNINGS", raising=False)

    class Owner:
        pass

    owner = Owner()
    with warnings.catch_warnings():
        registry.hold("host_warnings", owner)
        assert host_warnings_shown()
    try:
        assert "host_warnings" in registry.in_force() and not host_warnings_shown()
        assert not _shown(INDEXING, UserWarning, "nerfstudio.cameras.cameras")
    finally:
        registry.release("host_warnings", id(owner))
    assert not host_warnings_shown()


def test_the_environment_switch_keeps_every_warning(monkeypatch):
    monkeypatch.setenv("SP_HOST_WARNINGS", "1")
    assert _shown(INDEXING, UserWarning, "nerfstudio.cameras.cameras")
