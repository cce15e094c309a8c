"""No import cycle among the modules of ``sp_plugins`` (issue 45): see :mod:`tests.adapter.import_graph`
for what counts as an import (module level, and inside a function unless it defers a host)."""

from __future__ import annotations

from tests.adapter.import_graph import cycles, graph


def test_the_package_has_no_import_cycle():
    g = graph()
    assert len(g) > 100 and "sp_plugins.nerfstudio.seam" in g["sp_plugins.nerfstudio.model"]  # the walk sees the package
    found = cycles(g)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_a_function_level_import_counts_unless_it_defers_a_host():
    g = graph()
    # core/config names the preconditioner as its _target: a module-level import, the other way type-only
    assert "sp_plugins.core.preconditioner" in g["sp_plugins.core.config"]
    assert "sp_plugins.core.config" not in g["sp_plugins.core.preconditioner"]
    # sdfstudio's registration stays cheap for plugin discovery: it loads the host's variants inside with_sp
    assert "sp_plugins.sdfstudio.variants" not in g["sp_plugins.sdfstudio.registration"]
    assert "sp_plugins.sdfstudio.registration" in g["sp_plugins.sdfstudio.model"]
