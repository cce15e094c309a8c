"""Shared fixtures of the sweep tests: a tiny scene, a tiny mesh, the sp-sweep command."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest
import trimesh
from trimesh.exchange.ply import export_ply


@pytest.fixture(scope="session")
def sweep_scene(tmp_path_factory) -> Path:
    """8 training views of a 32x32 sphere (scene root: blender/, sdfstudio/, gt_mesh.ply)."""
    from sp_plugins.data import make_tiny_scene

    return make_tiny_scene(tmp_path_factory.mktemp("sweep-scene") / "sphere", mesh="sphere").root


@pytest.fixture(scope="session")
def sweep_mesh(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sweep-mesh") / "sphere.ply"
    path.write_bytes(export_ply(trimesh.creation.icosphere(2, radius=3.0)))
    return path


@pytest.fixture(scope="session")
def sp_sweep() -> str:
    path = Path(sys.executable).parent / "sp-sweep"
    if not path.exists() and shutil.which("sp-sweep") is None:
        pytest.skip("sp-sweep is not installed (pip install -e '.[sweeps]')")
    return str(path if path.exists() else shutil.which("sp-sweep"))
