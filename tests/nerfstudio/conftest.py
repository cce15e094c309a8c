"""Shared fixtures: one tiny rendered scene and CPU-sized versions of our method configs."""

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
