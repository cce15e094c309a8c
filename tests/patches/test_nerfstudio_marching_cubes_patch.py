"""The CPU mesher for ``ns-export marching-cubes``: guards on nerfstudio, then the coarse-to-fine mesher behind it."""

import importlib.metadata
import inspect
import sys
import types

import numpy as np
import pytest
import torch

pytest.importorskip("nerfstudio")

from nerfstudio.exporter import marching_cubes as ns_mc

from sp_plugins.patches import nerfstudio_marching_cubes as patch


@pytest.fixture(autouse=True)
def _collect_models_of_earlier_files():
    """A model built by an earlier test file in this process (an xdist worker runs many files) may be
    cyclic garbage that still holds the CPU mesher (``registry.hold``) until the next collection: the
    tests here start from nerfstudio's own mesher."""
    import gc

    gc.collect()


def test_nerfstudio_still_needs_the_patch_and_matches_its_signature():
    version = importlib.metadata.version("nerfstudio")
    assert version in patch.TESTED_NERFSTUDIO_VERSIONS, (
        f"nerfstudio {version} was not verified against the CPU marching-cubes patch: re-check "
        "nerfstudio/exporter/marching_cubes.py and update patches/nerfstudio_marching_cubes.py"
    )
    assert patch.check_nerfstudio_marching_cubes() == version
    original = patch._originals.get(patch.MODULES[0], getattr(ns_mc, patch.FUNCTION))
    assert ".cuda()" in inspect.getsource(original), "nerfstudio's mesher no longer hard-codes CUDA: drop the patch?"


def test_the_scope_rebinds_both_names_and_restores_them():
    from sp_plugins.patches import registry

    original = getattr(ns_mc, patch.FUNCTION)
    exporter = types.ModuleType(patch.MODULES[1])  # (importing ns-export's module takes 30 s here: its name binding only)
    exporter.generate_mesh_with_multires_marching_cubes = original
    saved = sys.modules.get(patch.MODULES[1])
    sys.modules[patch.MODULES[1]] = saved or exporter
    exporter = sys.modules[patch.MODULES[1]]
    try:
        assert exporter.generate_mesh_with_multires_marching_cubes is original
        with registry.scope(patch.PATCH.name, force=True) as active:
            assert active and getattr(ns_mc, patch.FUNCTION) is patch.scoped_marching_cubes
            assert exporter.generate_mesh_with_multires_marching_cubes is patch.scoped_marching_cubes
        assert getattr(ns_mc, patch.FUNCTION) is original and exporter.generate_mesh_with_multires_marching_cubes is original
    finally:
        if saved is None:
            del sys.modules[patch.MODULES[1]]
    assert patch._originals == {}


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


def _our_model():
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    config = methods["sp-neus-hashgrid"].pipeline.model
    config.sdf_field.num_levels, config.sdf_field.max_res, config.sdf_field.log2_hashmap_size = 4, 32, 10
    return config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2)


def test_only_an_sdf_of_our_field_gets_the_cpu_mesher_and_only_while_our_model_exists(monkeypatch):
    """What ns-export hands the mesher: a callable over its pipeline. Ours is recognised by our field's
    own forward_geonetwork answering the probe; any other SDF goes to nerfstudio's mesher."""
    import gc

    from sp_plugins.patches import registry

    original = getattr(ns_mc, patch.FUNCTION)
    model = _our_model()
    assert patch.PATCH.name in registry.held() and getattr(ns_mc, patch.FUNCTION) is patch.scoped_marching_cubes
    calls = []
    monkeypatch.setitem(patch._originals, patch.MODULES[0], lambda *args: calls.append(args) or "host mesher")
    other = torch.nn.Linear(3, 1)
    assert patch.scoped_marching_cubes(lambda x: other(x)[:, 0], resolution=16) == "host mesher" and len(calls) == 1
    assert patch.scoped_marching_cubes(_sphere, resolution=16) == "host mesher" and len(calls) == 2
    # F821 waived on the next two lines: pyflakes takes the lambdas' `model` for the name deleted below (they run before)
    assert patch.evaluates_our_field(lambda x: model.field.forward_geonetwork(x)[:, 0])  # noqa: F821
    mesh = patch.scoped_marching_cubes(lambda x: model.field.forward_geonetwork(x)[:, 0] * 0 + _sphere(x), resolution=32)  # noqa: F821
    assert len(calls) == 2 and mesh.is_watertight
    monkeypatch.undo()
    del model
    gc.collect()
    assert patch.PATCH.name not in registry.held() and getattr(ns_mc, patch.FUNCTION) is original
