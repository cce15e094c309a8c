"""Shared fixtures: one tiny rendered scene, CPU-sized versions of our method configs, and one fork
server for the nerfstudio commands."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.ns_configs import tiny_sdf_config


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """8 training views of a 32x32 sphere in both layouts (scene root)."""
    from sp_plugins.data import make_tiny_scene

    return make_tiny_scene(tmp_path_factory.mktemp("scene") / "sphere", mesh="sphere").root


@pytest.fixture
def tiny_config():
    """``tiny_config(name, scene, out, layout=, steps=, **sp_overrides)`` -> a small TrainerConfig."""
    return tiny_sdf_config


@pytest.fixture(scope="session")
def ns_server():
    """The test fork server (``tests/helpers/forkserver.py``) with nerfstudio's ``ns-train``, ``ns-eval``
    and ``ns-render`` imported once for the whole session (per xdist worker): a command forked from it
    skips the 15-30 s of imports a new interpreter pays. Only nerfstudio's own scripts are preloaded, so
    a forked ``ns-train`` has imported what the real one has (our console scripts, e.g.
    ``sp-export-mesh``, are imported by the child that runs them). Tests that check a real script start
    one with :mod:`subprocess` instead."""
    from tests.helpers.forkserver import ForkServer
    from tests.helpers.ns_commands import ENV

    server = ForkServer(["ns-train", "ns-eval", "ns-render"], ENV)
    yield server
    server.close()
