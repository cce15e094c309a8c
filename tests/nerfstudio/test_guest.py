"""Installing sp-plugins changes nothing for methods that are not ours.

nerfstudio imports every plugin's method configs in every ``ns-*`` command. In a fresh process we
snapshot what a plugin could change (the exception hook, the warning filters, the host names our
patches rebind, ``dataclasses.dataclass``), let nerfstudio discover its plugins, and compare.
Building one of our SDF models then must leave nerfstudio's ``tcnn`` and torchmetrics' LPIPS as they
were (their registry scopes end with the build); while the model exists the patches it holds (the
one-line error hook, the warning filters, the CPU mesher without CUDA) are in force, and the mesher
still sends another model's SDF to nerfstudio's own; once the model is gone everything is as before
discovery. (The sdfstudio counterpart, one run in a fresh process, is in
``tests/sdfstudio/test_patches.py``.)
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from tests.helpers.ns_commands import ENV

pytest.importorskip("nerfstudio")

SNAPSHOT = r'''
import sys, warnings, importlib, dataclasses, gc
for name in ("nerfstudio.engine.trainer", "nerfstudio.pipelines.base_pipeline", "nerfstudio.models.nerfacto",
             "nerfstudio.models.vanilla_nerf", "nerfstudio.models.tensorf", "nerfstudio.models.mipnerf",
             "nerfstudio.models.neus", "nerfstudio.fields.sdf_field", "nerfstudio.exporter.marching_cubes",
             "nerfstudio.configs.external_methods", "nerfstudio.data.datamanagers.base_datamanager",
             "nerfstudio.data.dataparsers.sdfstudio_dataparser", "nerfstudio.data.datasets.sdf_dataset",
             "torchmetrics.image.lpip", "nerfstudio.plugins.registry"):
    importlib.import_module(name)
import nerfstudio.models.nerfacto as nerfacto, nerfstudio.models.vanilla_nerf as vanilla, nerfstudio.models.tensorf as tensorf
import nerfstudio.models.mipnerf as mipnerf, nerfstudio.fields.sdf_field as sdf_field
import nerfstudio.exporter.marching_cubes as mc, nerfstudio.configs.external_methods as em, torchmetrics.image.lpip as lpip

def state():
    return {
        "excepthook": sys.excepthook,
        "filters": list(warnings.filters),
        "post_init": em.ExternalMethodDummyTrainerConfig.__post_init__,
        "tcnn": sdf_field.tcnn,
        "mesher": mc.generate_mesh_with_multires_marching_cubes,
        "fields": (nerfacto.NerfactoField, vanilla.NeRFField, tensorf.TensoRFField, mipnerf.NeRFField),
        "lpips": lpip.LearnedPerceptualImagePatchSimilarity,
        "dataclass": dataclasses.dataclass,
    }

before = state()
from nerfstudio.plugins.registry import discover_methods
methods, _ = discover_methods()
assert {"sp-neus-hashgrid", "sp-nerfacto", "sp-relu-field"} <= set(methods), sorted(methods)
after = state()
changed = [key for key in before if before[key] != after[key]]
print("CHANGED_BY_DISCOVERY", changed)
'''

BUILD = r'''
import torch
from nerfstudio.data.scene_box import SceneBox
from sp_plugins.patches import nerfstudio_marching_cubes as patch, registry
config = methods["sp-neus-hashgrid"].pipeline.model
config.sdf_field.num_levels, config.sdf_field.max_res, config.sdf_field.log2_hashmap_size = 4, 32, 10
model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2)
print("TCNN_RESTORED", sdf_field.tcnn is before["tcnn"])
print("LPIPS_RESTORED", lpip.LearnedPerceptualImagePatchSimilarity is before["lpips"])
print("HELD_BY_OUR_MODEL", sorted(registry.held()))
ours = lambda x: model.field.forward_geonetwork(x)[:, 0] * 0 + x.norm(dim=-1) - 0.5  # what ns-export passes, on a sphere
if torch.cuda.is_available():  # nerfstudio's own mesher serves everything: nothing is installed
    print("MESHER_UNTOUCHED", mc.generate_mesh_with_multires_marching_cubes is before["mesher"])
else:
    calls = []
    host = patch._originals[patch.MODULES[0]]
    patch._originals[patch.MODULES[0]] = lambda *a: calls.append(1) or "host"  # nerfstudio's mesher needs CUDA: count the calls
    other = torch.nn.Linear(3, 1)  # an SDF that is not ours
    print("OTHER_GOES_TO_HOST", mc.generate_mesh_with_multires_marching_cubes(lambda x: other(x)[:, 0], resolution=16) == "host")
    print("OURS_ON_CPU", len(mc.generate_mesh_with_multires_marching_cubes(ours, resolution=16).faces) > 0 and len(calls) == 1)
    patch._originals[patch.MODULES[0]] = host
del model, ours
gc.collect()
after = state()
print("CHANGED_AFTER_OUR_MODEL", [key for key in before if before[key] != after[key]], sorted(registry.held()))
'''


def run_python(code: str) -> str:
    proc = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc.stdout


def test_discovering_our_methods_changes_nothing_and_building_ours_is_scoped():
    out = run_python(SNAPSHOT + BUILD)
    assert "CHANGED_BY_DISCOVERY []" in out, out
    assert "TCNN_RESTORED True" in out and "LPIPS_RESTORED True" in out, out
    import torch

    if torch.cuda.is_available():
        assert "HELD_BY_OUR_MODEL []" in out and "MESHER_UNTOUCHED True" in out, out
    else:
        # building our model installs no hook and filters no warning: only the mesher it serves
        assert "HELD_BY_OUR_MODEL ['nerfstudio_marching_cubes']" in out, out
        assert "OTHER_GOES_TO_HOST True" in out, out
        assert "OURS_ON_CPU True" in out, out
    assert "CHANGED_AFTER_OUR_MODEL [] []" in out, out
