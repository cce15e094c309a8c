"""No import cycle among the modules of ``sp_plugins``, counting every import: at
module level, inside functions and under ``TYPE_CHECKING`` (:mod:`tests.adapter.import_graph`)."""

from __future__ import annotations

import pytest

from tests.adapter.import_graph import KINDS, cycles, graph, host_loaders


@pytest.mark.parametrize("upto", range(1, len(KINDS) + 1), ids=["module", "plus-function", "plus-type-checking"])
def test_the_package_has_no_import_cycle(upto):
    g = graph(KINDS[:upto])
    assert len(g) > 100 and "sp_plugins.nerfstudio.seam" in g["sp_plugins.nerfstudio.model"]  # the walk sees the package
    found = cycles(g)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_every_kind_of_import_is_an_edge():
    """A function-level and a TYPE_CHECKING import are edges (a cycle through one is still found)."""
    assert "sp_plugins.sdfstudio.variants" in graph(["function"])["sp_plugins.sdfstudio.registration"]
    assert "sp_plugins.sdfstudio.variants" not in graph(["module"])["sp_plugins.sdfstudio.registration"]
    assert "sp_plugins.core" in graph(["type_checking"])["sp_plugins.sdfstudio.registration"]
    assert cycles({"a": {"b"}, "b": {"a"}, "c": set()}) == [["a", "b"]]


def test_registration_modules_stay_cheap():
    """A host's plugin discovery imports its registration module: it loads no host, and defers the
    modules that do to the functions that need them."""
    loaders = host_loaders()
    assert "sp_plugins.nerfstudio.seam" in loaders and "sp_plugins.sdfstudio.variants" in loaders
    for module in ("sp_plugins.nerfstudio.registration", "sp_plugins.sdfstudio.registration", "sp_plugins.nerfstudio.table",
                   "sp_plugins.sdfstudio.table"):
        assert module not in loaders, module


def test_the_preconditioner_reads_settings_not_the_config():
    """core/config names the preconditioner as its _target; the preconditioner reads only the settings."""
    g = graph()
    assert "sp_plugins.core.preconditioner" in g["sp_plugins.core.config"]
    assert "sp_plugins.core.config" not in g["sp_plugins.core.preconditioner"]
    assert "sp_plugins.core.settings" in g["sp_plugins.core.preconditioner"]
