"""The CPU mesher for ``ns-export marching-cubes``: guards on nerfstudio, then the coarse-to-fine mesher behind it."""

import functools
import importlib.metadata
import inspect
import sys

import numpy as np
import pytest
import torch

pytest.importorskip("nerfstudio")

from nerfstudio.exporter import marching_cubes as ns_mc  # noqa: E402

from sp_plugins.patches import nerfstudio_marching_cubes as patch  # noqa: E402


def test_nerfstudio_still_needs_the_patch_and_matches_its_signature():
    version = importlib.metadata.version("nerfstudio")
    assert version in patch.TESTED_NERFSTUDIO_VERSIONS, (
        f"nerfstudio {version} was not verified against the CPU marching-cubes patch: re-check "
        "nerfstudio/exporter/marching_cubes.py and update patches/nerfstudio_marching_cubes.py"
    )
    assert patch.check_nerfstudio_marching_cubes() == version
    original = patch._originals.get(patch.MODULES[0], getattr(ns_mc, patch.FUNCTION))
    assert ".cuda()" in inspect.getsource(original), "nerfstudio's mesher no longer hard-codes CUDA: drop the patch?"


def test_install_rebinds_both_names_and_uninstall_restores():
    was = dict(patch._originals)
    original = was.get(patch.MODULES[0], getattr(ns_mc, patch.FUNCTION))
    try:
        patch.uninstall_cpu_marching_cubes()
        assert getattr(ns_mc, patch.FUNCTION) is original
        assert patch.install_cpu_marching_cubes(force=True)
        assert getattr(ns_mc, patch.FUNCTION) is patch.scoped_marching_cubes
        exporter = sys.modules.get("nerfstudio.scripts.exporter")
        if exporter is not None:
            assert exporter.generate_mesh_with_multires_marching_cubes is patch.scoped_marching_cubes
        patch.uninstall_cpu_marching_cubes()
        assert getattr(ns_mc, patch.FUNCTION) is original
    finally:
        if was:
            patch.install_cpu_marching_cubes(force=True)


def _sphere(points):
    return points.norm(dim=-1) - 0.5


def test_the_patch_meshes_near_the_surface_only_at_any_resolution():
    calls = []

    def counted(points):
        calls.append(len(points))
        return _sphere(points)

    mesh = patch.cpu_marching_cubes(counted, resolution=128)  # nerfstudio's own mesher needs 512k
    assert sum(calls) < 0.2 * 129**3 and mesh.is_watertight


def test_cpu_marching_cubes_meshes_a_sphere_outward():
    mesh = patch.cpu_marching_cubes(_sphere, resolution=64)
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert abs(radii.mean() - 0.5) < 2e-3 and radii.max() - radii.min() < 2 / 64
    assert mesh.is_watertight and mesh.volume > 0
    with pytest.raises(ValueError, match="does not cross"):
        patch.cpu_marching_cubes(lambda p: p.norm(dim=-1) + 1.0, resolution=16)


def test_only_claimed_models_get_the_cpu_mesher(monkeypatch):
    """The rebinding is scoped: the SDF of a model that is not ours goes to nerfstudio's own mesher."""
    calls = []
    patch.install_cpu_marching_cubes(force=True)  # the host's mesher is recorded before we stand in for it
    host = functools.wraps(patch._originals[patch.MODULES[0]])(lambda *args: calls.append(args) or "host mesher")
    monkeypatch.setitem(patch._originals, patch.MODULES[0], host)
    ours, theirs = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1)

    class Pipeline:
        def __init__(self, model):
            self.model = model

    def exporter_closure(pipeline):  # what ns-export passes: a lambda over its pipeline
        return lambda x: _sphere(x) + 0 * len(str(pipeline))

    patch.claim_for_cpu_marching_cubes(ours, force=True)
    assert patch.scoped_marching_cubes(exporter_closure(Pipeline(theirs)), resolution=16) == "host mesher"
    assert len(calls) == 1
    mesh = patch.scoped_marching_cubes(exporter_closure(Pipeline(ours)), resolution=32)
    assert len(calls) == 1 and mesh.is_watertight
