"""The sdfstudio compatibility patches (commit 370902a): each still needed by the host, each doing
its job, none reaching outside sdfstudio's modules."""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
import subprocess
import sys
from types import SimpleNamespace

from pathlib import Path

import pytest
import torch

from tests.helpers.sdf_configs import env

pytestmark = pytest.mark.usefixtures("patched")


def unpatched_python(code: str) -> subprocess.CompletedProcess:
    """Python in this venv without our hook (so: sdfstudio as shipped)."""
    e = env()
    e["SP_SDFSTUDIO_HOOK"] = "0"
    return subprocess.run([sys.executable, "-c", code], env=e, capture_output=True, text=True, timeout=120)


def test_host_still_needs_the_patches_and_imports_with_them():
    """Fails loudly when sdfstudio changes: as shipped it cannot be imported on this Python/torch."""
    proc = unpatched_python("import nerfstudio.configs.base_config")
    assert proc.returncode != 0 and "mutable default" in proc.stderr, proc.stderr[-500:]
    proc = unpatched_python("import torch._six")
    assert proc.returncode != 0 and "torch._six" in proc.stderr


def test_mutable_defaults_become_fresh_copies_only_in_sdfstudio_modules():
    from nerfstudio.fields.sdf_field import SDFFieldConfig
    from nerfstudio.models.base_surface_model import SurfaceModelConfig

    a, b = SurfaceModelConfig(), SurfaceModelConfig()
    assert isinstance(a.sdf_field, SDFFieldConfig) and a.sdf_field == b.sdf_field and a.sdf_field is not b.sdf_field
    with pytest.raises(ValueError, match="mutable default"):  # our own classes keep Python's rule

        @dataclasses.dataclass
        class Outer:
            inner: SDFFieldConfig = SDFFieldConfig()


def test_torch_six_stand_in():
    from nerfstudio.data.utils import nerfstudio_collate

    assert nerfstudio_collate.string_classes == (str,)


def test_lpips_never_downloads(tmp_path, monkeypatch):
    import nerfstudio.models.base_surface_model as bsm

    from sp_plugins.patches.sdfstudio_lpips import MissingLPIPS

    def no_network(*args, **kwargs):
        raise AssertionError("LPIPS tried to download")

    monkeypatch.setattr(torch.hub, "download_url_to_file", no_network)
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    metric = bsm.LearnedPerceptualImagePatchSimilarity()
    assert isinstance(metric, MissingLPIPS) and torch.isnan(metric(torch.zeros(1), torch.zeros(1)))
    assert bsm.LearnedPerceptualImagePatchSimilarity.real.__name__ == "LearnedPerceptualImagePatchSimilarity"


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the CPU meaning of CUDA-only calls")
def test_cuda_only_calls_run_on_the_cpu():
    import scripts.extract_mesh as extract_mesh
    import scripts.train as train
    from nerfstudio.utils import marching_cubes, writer

    from sp_plugins.patches.sdfstudio_cuda import CPU_TORCH, cpu_meaning

    # the host still makes these calls (fails loudly when sdfstudio changes)
    assert "torch.cuda.synchronize()" in inspect.getsource(writer.TimeWriter.__enter__)
    assert "torch.cuda.set_device" in inspect.getsource(train.train_loop)
    assert ".cuda()" in inspect.getsource(marching_cubes.get_surface_sliding.__wrapped__)
    assert extract_mesh.get_surface_sliding is marching_cubes.get_surface_sliding
    # only the writer's and the train loop's own `torch` is the CPU view; torch itself is untouched
    assert writer.torch is CPU_TORCH and train.torch is CPU_TORCH and CPU_TORCH.Tensor is torch.Tensor
    with pytest.raises((RuntimeError, AssertionError)):  # torch's own: no CUDA here
        torch.cuda.synchronize()
    with writer.TimeWriter(None, "x", write=False) as timer:
        pass
    assert timer.duration >= 0
    saved = torch.Tensor.cuda, torch.cuda.synchronize, torch.cuda.set_device
    t = torch.ones(2)
    with cpu_meaning():
        with pytest.raises((RuntimeError, AssertionError)):  # our code (this test) still gets torch's meaning
            t.cuda()
        host_code = {"__name__": "nerfstudio.utils.marching_cubes", "t": t}  # code that runs as sdfstudio's
        exec("moved = t.cuda()", host_code)
        assert host_code["moved"] is t
    assert (torch.Tensor.cuda, torch.cuda.synchronize, torch.cuda.set_device) == saved


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the CPU meaning of CUDA-only calls")
def test_pair_loading_runs_on_the_cpu_outside_train_loop(sdf_scene, tmp_path):
    """GeoNeuS patch warping (--load-pairs True) moves the images with .cuda() in the parser, which
    ns-eval / eval_setup run outside train_loop."""
    import json
    import shutil

    from nerfstudio.data.dataparsers import sdfstudio_dataparser
    from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig

    from tests.helpers.sdf_configs import pairs_file

    assert ".cuda()" in inspect.getsource(sdfstudio_dataparser.SDFStudio._generate_dataparser_outputs.__wrapped__)
    scene = tmp_path / "scene"
    shutil.copytree(sdf_scene, scene)
    frames = len(json.loads((scene / "meta_data.json").read_text())["frames"])
    pairs_file(scene, frames)
    outputs = SDFStudioDataParserConfig(data=scene, load_pairs=True).setup().get_dataparser_outputs("train")
    images = outputs.additional_inputs["pairs"]["kwargs"]["all_imgs"]
    assert images.device.type == "cpu" and len(images) == frames


def test_tcnn_stand_in_is_given_to_sdfstudio_only():
    import nerfstudio.fields.density_fields as density_fields
    import nerfstudio.fields.sdf_field as sdf_field

    from sp_plugins.patches import sdfstudio_tcnn

    assert importlib.util.find_spec("tinycudann") is None, "these checks are for a machine without tiny-cuda-nn"
    assert sdf_field.tcnn is sdfstudio_tcnn and density_fields.tcnn is sdfstudio_tcnn
    assert "tinycudann" not in sys.modules  # never registered under tcnn's name

    class WithRealTcnn:
        tcnn = object()

    real = WithRealTcnn.tcnn
    sdfstudio_tcnn._give_stand_in(WithRealTcnn)
    assert WithRealTcnn.tcnn is real


def test_tcnn_stand_in_modules():
    from nerfstudio.utils.math import components_from_spherical_harmonics

    from sp_plugins.encodings import HashGrid
    from sp_plugins.patches import sdfstudio_tcnn as tcnn

    grid_config = {"otype": "HashGrid", "n_levels": 4, "n_features_per_level": 2, "log2_hashmap_size": 10,
                   "base_resolution": 4, "per_level_scale": 1.5, "interpolation": "Linear"}
    enc = tcnn.Encoding(3, grid_config)
    assert isinstance(enc, HashGrid) and enc.n_output_dims == 8 and enc.backend == "torch"
    x = torch.rand(7, 3, requires_grad=True)
    assert enc(x).shape == (7, 8)

    net = tcnn.NetworkWithInputEncoding(3, 1, grid_config, {"otype": "FullyFusedMLP", "activation": "ReLU",
                                                            "output_activation": "None", "n_neurons": 16, "n_hidden_layers": 1})
    net(x).sum().backward()
    assert x.grad is not None and all(p.grad is not None for p in net.parameters())
    assert [tuple(p.shape) for p in net.network.parameters()] == [(16, 8), (1, 16)]  # no biases, as in tcnn

    sh = tcnn.Encoding(3, {"otype": "SphericalHarmonics", "degree": 4})
    d = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    torch.testing.assert_close(sh((d + 1) / 2), components_from_spherical_harmonics(4, d))
    freq = tcnn.Encoding(3, {"otype": "Frequency", "n_frequencies": 2})
    assert freq(torch.rand(5, 3)).shape == (5, freq.n_output_dims) == (5, 12)
    head = tcnn.Network(4, 3, {"activation": "ReLU", "output_activation": "Sigmoid", "n_neurons": 8, "n_hidden_layers": 2})
    y = head(torch.randn(6, 4))
    assert y.shape == (6, 3) and ((0 < y) & (y < 1)).all()
    with pytest.raises(NotImplementedError, match="OneBlob"):
        tcnn.Encoding(3, {"otype": "OneBlob"})


def test_only_sdfstudio_modules_go_through_the_patching_loader():
    import nerfstudio.fields.sdf_field as sdf_field
    import scripts.train as train

    from sp_plugins.patches.sdfstudio_import_hook import _PatchingLoader

    assert isinstance(sdf_field.__spec__.loader, _PatchingLoader) and isinstance(train.__spec__.loader, _PatchingLoader)
    assert not isinstance(torch.__spec__.loader, _PatchingLoader)
    assert "class SDFField" in inspect.getsource(sdf_field)  # the wrapped loader still serves sources


def test_opt_in_hook_waits_for_sdfstudio_and_can_be_switched_off():
    """The .pth hook installed by ./run.sh setup-sdfstudio: one waiting finder at start-up, the
    patching finder only once sdfstudio's nerfstudio is imported, nothing with SP_SDFSTUDIO_HOOK=0."""
    from sp_plugins.sdfstudio.hook import pth_path

    assert pth_path().is_file(), "run: python -m sp_plugins.sdfstudio.hook install"
    names = "import sys; print(sorted(type(f).__name__ for f in sys.meta_path if 'First' in type(f).__name__ or 'Sdfstudio' in type(f).__name__))"
    waiting = subprocess.run([sys.executable, "-c", names], env=env(), capture_output=True, text=True, timeout=60)
    assert waiting.stdout.strip() == "['_FirstImport']", waiting.stdout + waiting.stderr[-500:]
    active = subprocess.run([sys.executable, "-c", "import nerfstudio; " + names], env=env(), capture_output=True, text=True, timeout=120)
    assert active.stdout.strip() == "['SdfstudioFinder']", active.stdout + active.stderr[-500:]
    off = unpatched_python(names)
    assert off.stdout.strip() == "[]", off.stdout + off.stderr[-500:]


def test_our_install_beside_the_waiting_hook_enters_each_patch_once_and_exits_cleanly():
    """sp-sdfstudio-* and the bench install every sdfstudio patch themselves while the .pth hook still
    waits: the import hook's guard looks sdfstudio up, which fires the hook, which installs them all
    again from inside the first install. Each patch must be in force once, and the process must end
    without an error (it printed a KeyError from the registry's atexit handler)."""
    code = ("from sp_plugins.patches import registry; from sp_plugins.patches.sdfstudio_import_hook import install_all; "
            "install_all(); import nerfstudio; print(sorted(registry._installed))")
    proc = subprocess.run([sys.executable, "-c", code], env=env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "sdfstudio_import_hook" in proc.stdout, proc.stdout
    assert "Exception ignored" not in proc.stderr and "KeyError" not in proc.stderr, proc.stderr[-2000:]


def test_checkpoints_with_numpy_learning_rates_load_in_sdfstudio_and_nowhere_else(tmp_path):
    """Past its warm-up sdfstudio's NeuSScheduler (and MultiStepWarmupScheduler, and
    ExponentialDecaySchedule from the start) leaves numpy float64 learning rates in every checkpoint;
    torch >= 2.6 loads weights-only by default and refused them in both of sdfstudio's loads
    (--trainer.load-dir, eval_setup): a real run could be neither resumed nor evaluated after 5000
    steps. The patch allows numpy scalars there and only there (found by the kill and resume test)."""
    import numpy as np
    from nerfstudio.engine.schedulers import NeuSScheduler
    from nerfstudio.engine.trainer import Trainer
    from nerfstudio.utils import eval_utils

    # the host still loads weights-only by default and still makes numpy learning rates (fails loudly when either changes)
    for fn in (Trainer._load_checkpoint, eval_utils.eval_load_checkpoint):
        assert 'torch.load(load_path, map_location="cpu")' in inspect.getsource(fn.__wrapped__), fn.__name__
    optimizer = torch.optim.Adam([torch.nn.Parameter(torch.zeros(2))], lr=1e-3)
    scheduler = NeuSScheduler(optimizer, warm_up_end=1, learning_rate_alpha=0.05, max_steps=10)
    optimizer.step()
    scheduler.step()
    assert isinstance(scheduler.get_last_lr()[0], np.float64)

    class Pipeline:
        loaded = None

        def load_pipeline(self, state):
            self.loaded = state

    state = {"step": 7, "pipeline": {"w": torch.ones(2)}, "optimizers": {"fields": optimizer.state_dict()},
             "schedulers": {"fields": scheduler.state_dict()}, "scalers": {}}
    (tmp_path / "sdfstudio_models").mkdir()
    path = tmp_path / "sdfstudio_models" / "step-000000007.ckpt"
    torch.save(state, path)
    with pytest.raises(Exception, match="Weights only load failed"):  # elsewhere torch's default stays
        torch.load(path, map_location="cpu")
    with pytest.raises(Exception, match="Weights only load failed"):  # what sdfstudio did unpatched
        eval_utils.eval_load_checkpoint.__wrapped__(SimpleNamespace(load_dir=tmp_path / "sdfstudio_models", load_step=None), Pipeline())

    pipeline = Pipeline()
    assert eval_utils.eval_load_checkpoint(SimpleNamespace(load_dir=tmp_path / "sdfstudio_models", load_step=None), pipeline) == path
    assert torch.equal(pipeline.loaded["w"], torch.ones(2))

    optimizers = SimpleNamespace(loaded=None)
    optimizers.load_optimizers = lambda s: setattr(optimizers, "loaded", s)
    optimizers.load_schedulers = lambda s: None
    trainer = SimpleNamespace(config=SimpleNamespace(trainer=SimpleNamespace(load_dir=tmp_path / "sdfstudio_models", load_step=None, load_scheduler=True)),
                              pipeline=Pipeline(), optimizers=optimizers, grad_scaler=SimpleNamespace(load_state_dict=lambda s: None))
    Trainer._load_checkpoint(trainer)
    assert trainer._start_step == 8 and optimizers.loaded["fields"]["param_groups"][0]["lr"] == scheduler.get_last_lr()[0]
    with pytest.raises(Exception, match="Weights only load failed"):  # and after it, torch's default again
        torch.load(path, map_location="cpu")


# -- the registry: every sdfstudio entry guarded; after each scope the host as it was --------------------


def _sdfstudio_entries():
    from sp_plugins.patches import registry

    return [p for p in registry.entries("sdfstudio")]


def test_every_sdfstudio_entry_is_guarded(monkeypatch):
    from sp_plugins.patches import sdfstudio_import_hook
    from sp_plugins.patches.registry import PatchGuardError

    entries = _sdfstudio_entries()
    assert {p.name for p in entries} >= {"sdfstudio_import_hook", "sdfstudio_dataclasses", "sdfstudio_torch_six", "sdfstudio_cuda",
                                         "sdfstudio_lpips", "sdfstudio_tcnn", "sdfstudio_checkpoint_load", "sdfstudio_methods"}
    real_source = sdfstudio_import_hook.host_source
    for patch in entries:
        patch.guard()
        assert patch.guarded, patch.name
        for where, attr in patch.guarded:
            with monkeypatch.context() as m:
                if where == sdfstudio_import_hook.SOURCE:  # sdfstudio's file no longer holds what the patch fixes
                    m.setattr(sdfstudio_import_hook, "host_source", lambda rel, attr=attr: "" if rel == attr else real_source(rel))
                else:
                    owner = importlib.import_module(where) if where != "torch.Tensor" else torch.Tensor
                    m.setattr(owner, attr, object())
                with pytest.raises(PatchGuardError) as failure:
                    patch.guard()
            message = str(failure.value)
            assert "\n" not in message and f"patch {patch.name}:" in message and "written for sdfstudio 370902a" in message, message
            assert attr in message or attr.rsplit("/", 1)[-1] in message, message


SCOPES = r"""
import dataclasses, gc, importlib, sys, warnings, torch
from sp_plugins.patches import registry, sdfstudio_import_hook as hook

def state():
    return {"dataclass": dataclasses.dataclass, "excepthook": sys.excepthook, "filters": warnings.filters,
            "filter_entries": list(warnings.filters), "meta_path": list(sys.meta_path), "six": "torch._six" in sys.modules,
            "cuda": (torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda), "modules": dict(sys.modules)}

from sp_plugins.patches.host_warnings import HOST_WARNINGS
OURS = {message for _, message, _ in HOST_WARNINGS}

def changed(before, after):
    out = [k for k in before if k not in ("modules", "filter_entries", "meta_path") and
           (before[k] != after[k] if isinstance(before[k], (bool, tuple)) else before[k] is not after[k])]
    # what sdfstudio's third-party imports add themselves (absl's reload detector, numpy's and torch's filters) is
    # not ours: nothing of ours may be added, nothing that was there may go
    out += ["meta_path"] * (any(f not in after["meta_path"] for f in before["meta_path"])
                            or any(type(f).__module__.startswith("sp_plugins") for f in after["meta_path"]))
    out += ["filter_entries"] * (any(f not in after["filter_entries"] for f in before["filter_entries"])
                                 or any(getattr(f[1], "pattern", None) in OURS for f in after["filter_entries"]))
    return out + [n for n, m in before["modules"].items() if after["modules"].get(n) is not m]

before = state()
with registry.scope("sdfstudio_import_hook"), registry.scope("sdfstudio_dataclasses"), registry.scope("sdfstudio_torch_six"):
    import nerfstudio.configs.base_config as base_config         # needs the tolerant dataclass
    from nerfstudio.data.utils import nerfstudio_collate          # needs torch._six
    assert nerfstudio_collate.string_classes == (str,)
    assert base_config.dataclasses is not dataclasses if hasattr(base_config, "dataclasses") else True
    inside = state()
print("IMPORT_SCOPES_CHANGED", [k for k in changed(before, state()) if k != "modules"])
# every entry in turn, over modules already imported: each rebinding put back
for name in ("sdfstudio_cuda", "sdfstudio_lpips", "sdfstudio_tcnn", "sdfstudio_checkpoint_load"):
    with registry.scope("sdfstudio_import_hook"), registry.scope("sdfstudio_dataclasses"), registry.scope("sdfstudio_torch_six"):
        for module in ("nerfstudio.utils.writer", "nerfstudio.utils.marching_cubes", "nerfstudio.models.base_surface_model",
                       "nerfstudio.fields.sdf_field", "nerfstudio.engine.trainer", "nerfstudio.utils.eval_utils"):
            importlib.import_module(module)
    mods = {m: dict(vars(sys.modules[m])) for m in ("nerfstudio.utils.writer", "nerfstudio.utils.marching_cubes",
            "nerfstudio.models.base_surface_model", "nerfstudio.fields.sdf_field", "nerfstudio.utils.eval_utils")}
    classes = {c: dict(vars(c)) for c in (sys.modules["nerfstudio.engine.trainer"].Trainer,)}
    before = state()
    with registry.scope(name):
        differs = [m for m in mods if any(vars(sys.modules[m]).get(k) is not v for k, v in mods[m].items())]
        differs += [c.__name__ for c in classes if any(vars(c).get(k) is not v for k, v in classes[c].items())]
    after_mods = [m for m in mods if any(vars(sys.modules[m]).get(k) is not v for k, v in mods[m].items())]
    after_mods += [c.__name__ for c in classes if any(vars(c).get(k) is not v for k, v in classes[c].items())]
    print("SCOPE", name, "CHANGED_INSIDE", bool(differs) or name == "sdfstudio_tcnn", "AFTER", changed(before, state()) + after_mods)
"""


def test_after_each_sdfstudio_scope_the_host_is_as_it_was():
    """In a fresh process (no install_all): the import scopes let sdfstudio import and leave
    dataclasses, sys.modules, torch, the hook and the filters as they were; each rebinding scope
    changes sdfstudio's modules inside and puts them back after."""
    e = env()
    e["SP_SDFSTUDIO_HOOK"] = "0"
    proc = subprocess.run([sys.executable, "-c", SCOPES], env=e, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "IMPORT_SCOPES_CHANGED []" in out, out
    for name in ("sdfstudio_cuda", "sdfstudio_lpips", "sdfstudio_checkpoint_load"):
        assert f"SCOPE {name} CHANGED_INSIDE True AFTER []" in out, out
    assert "SCOPE sdfstudio_tcnn CHANGED_INSIDE True AFTER []" in out, out


GUEST_RUN = r"""
import dataclasses, sys, warnings, torch
from pathlib import Path
data, out = Path(sys.argv[1]), Path(sys.argv[2])
real = {"dataclass": dataclasses.dataclass, "excepthook": sys.excepthook, "filters": warnings.filters,
        "cuda": (torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda)}
from sp_plugins.patches.sdfstudio_import_hook import HOST_PACKAGES, install_all
install_all()  # what sp-sdfstudio-train does first
import scripts.train as train
import nerfstudio.configs.method_configs as host
from sp_plugins.patches import registry
registry.install_for_process("sdfstudio_methods", command="sp-sdfstudio-train")
from tests.helpers.sdf_configs import tiny_config
config = tiny_config(host.method_configs["sp-neus"], data, out, steps=2)
config.machine.num_gpus = 0
seen = {}
train.train_loop(local_rank=0, world_size=0, config=config)  # what main() runs for --machine.num-gpus 0
print("TRAINED", any(out.rglob("*.ckpt")))
leaks = [k for k, v in real.items() if (v != (torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda) if k == "cuda"
         else v is not {"dataclass": dataclasses.dataclass, "excepthook": sys.excepthook, "filters": warnings.filters}[k])]
print("PROCESS_LEAKS", leaks, "six" if "torch._six" in sys.modules else "")
from sp_plugins.patches.sdfstudio_dataclasses import TOLERANT, _tolerant_dataclass
tolerant = sorted(name for name, module in list(sys.modules.items())
                  if module is not None and name.partition(".")[0] not in HOST_PACKAGES
                  and name not in ("__main__", "__mp_main__", "sp_plugins.patches.sdfstudio_dataclasses")
                  and any(value is _tolerant_dataclass or value is TOLERANT for value in list(vars(module).values())))
print("OTHER_MODULES_WITH_OUR_DATACLASS", tolerant[:5])
host_tolerant = vars(sys.modules["nerfstudio.configs.base_config"])["dataclass"] is _tolerant_dataclass
print("SDFSTUDIO_HAS_ITS_OWN", host_tolerant)
try:
    import torch._six
    print("TORCH_SIX_IMPORTS_ELSEWHERE True")
except ImportError:
    print("TORCH_SIX_IMPORTS_ELSEWHERE False")
"""


@pytest.mark.skipif(torch.cuda.is_available(), reason="the CPU run")
def test_an_sdfstudio_run_leaves_the_rest_of_the_process_as_it_was(sdf_scene, tmp_path):
    """The guest test for sdfstudio: a fresh process with every sdfstudio patch (as
    sp-sdfstudio-train has them) trains sp-neus two steps through sdfstudio's own train_loop; then
    dataclasses.dataclass, sys.excepthook, warnings.filters and torch's CUDA functions are the
    objects they were, no module outside sdfstudio's packages holds our tolerant dataclass (the
    third-party ones sdfstudio imported first included), and torch._six exists only for sdfstudio."""
    import os

    e = env()
    e["SP_SDFSTUDIO_HOOK"] = "0"
    e["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[2]), e.get("PYTHONPATH", "")])
    proc = subprocess.run([sys.executable, "-c", GUEST_RUN, str(sdf_scene), str(tmp_path / "out")], env=e, capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "TRAINED True" in out, out
    assert "PROCESS_LEAKS [] \n" in out or "PROCESS_LEAKS [] " in out, out
    assert "OTHER_MODULES_WITH_OUR_DATACLASS []" in out, out
    assert "SDFSTUDIO_HAS_ITS_OWN True" in out and "TORCH_SIX_IMPORTS_ELSEWHERE False" in out, out
