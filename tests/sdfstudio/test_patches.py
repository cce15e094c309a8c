"""The sdfstudio compatibility patches (commit 370902a): each still needed by the host, each doing
its job, none reaching outside sdfstudio's modules."""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
import subprocess
import sys
from types import SimpleNamespace

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

    from sp_plugins.patches.sdfstudio_cuda import cpu_meaning

    # the host still makes these calls (fails loudly when sdfstudio changes)
    assert "torch.cuda.synchronize()" in inspect.getsource(writer.TimeWriter.__enter__.__wrapped__)
    assert "torch.cuda.set_device" in inspect.getsource(train.train_loop.__wrapped__)
    assert ".cuda()" in inspect.getsource(marching_cubes.get_surface_sliding.__wrapped__)
    assert extract_mesh.get_surface_sliding is marching_cubes.get_surface_sliding
    with pytest.raises((RuntimeError, AssertionError)):  # unpatched: no CUDA here
        writer.TimeWriter.__enter__.__wrapped__(writer.TimeWriter(None, "x", write=False))
    with writer.TimeWriter(None, "x", write=False) as timer:
        pass
    assert timer.duration >= 0
    saved = torch.Tensor.cuda, torch.cuda.synchronize
    with cpu_meaning():
        t = torch.ones(2)
        assert t.cuda() is t
    assert (torch.Tensor.cuda, torch.cuda.synchronize) == saved


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


def test_checkpoints_with_numpy_learning_rates_load_in_sdfstudio_and_nowhere_else(tmp_path):
    """Past its warm-up sdfstudio's NeuSScheduler (and MultiStepWarmupScheduler, and
    ExponentialDecaySchedule from the start) leaves numpy float64 learning rates in every checkpoint;
    torch >= 2.6 loads weights-only by default and refused them in both of sdfstudio's loads
    (--trainer.load-dir, eval_setup): a real run could be neither resumed nor evaluated after 5000
    steps. The patch allows numpy scalars there and only there (found by issue 22's kill and resume test)."""
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
