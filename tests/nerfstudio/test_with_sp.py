"""SP on any nerfstudio method: ``with_sp``, ``sp-train``, third-party plugins, refusals.

The plugin (``plugin_fixture/toyplugin``: its own ``Model`` and ``Field`` classes sp-plugins has
never seen) is installed as a temporary distribution with ``nerfstudio.method_configs`` entry
points, as a plugin author ships one. Its fields read positions each in their own way
(``get_positions()``, ``get_start_positions()`` with an eikonal gradient, ``get_gaussian_blob()``,
and one that reads them from the samples' metadata) and log, against the plain samples the model
made, how far what they read moved (``TOY_FIELD_LOG``).

The plugin methods' ``sp-train`` / ``ns-eval`` / ``ns-render`` runs are forked from one process that
imported those commands (and discovered the plugin) once (``tests/helpers/forkserver.py``); the help,
the refusals and the plugin's registration run the real scripts.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.helpers.forkserver import ForkServer
from tests.helpers.ns_commands import ENV, RUN_FLAGS, _report, command
from tests.helpers.sp_fields import perturbed_calls, sp_fields

pytest.importorskip("nerfstudio")

FIXTURE = Path(__file__).parent / "plugin_fixture"
STEPS = 4


def install_toy_plugin(root: Path) -> Path:
    """The toy plugin as a distribution in ``root`` (importable once ``root`` is on the path)."""
    shutil.copytree(FIXTURE / "toyplugin", root / "toyplugin")
    dist = root / "toyplugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: toyplugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(
        "[nerfstudio.method_configs]\ntoy-method = toyplugin.config:toy_method\nsp-toy-method = toyplugin.config:sp_toy_method\n"
        "toy-sdf = toyplugin.config:toy_sdf\ntoy-blob = toyplugin.config:toy_blob\ntoy-bypass = toyplugin.config:toy_bypass\n"
        "toy-download = toyplugin.config:toy_download\ntoy-nofield = toyplugin.config:toy_nofield\n"
    )
    return root


def run_env(args, env, timeout=600, expect=0):
    proc = subprocess.run([str(a) for a in args], env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == expect, _report(args, proc)
    return proc


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    root = install_toy_plugin(tmp_path_factory.mktemp("plugin"))
    env = dict(ENV, PYTHONPATH=os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p))
    return root, env


def log_lines(path: Path):
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def sp_train_toy(method, env, out, tiny_scene, log, expect=0, server=None):
    """``sp-train METHOD``: SP (alpha 0.05) for the first half of 4 steps, then plain (``server``: forked
    from the fork server instead of a new interpreter)."""
    args = [command("sp-train"), method, *RUN_FLAGS, "--max-num-iterations", STEPS, "--steps-per-save", STEPS,
            "--steps-per-eval-batch", 1000, "--steps-per-eval-image", 1000, "--steps-per-eval-all-images", 1000,
            "--output-dir", out, "--pipeline.model.sp.alpha0", "0.05", "--pipeline.model.sp.schedule", "step",
            "--pipeline.model.sp.end", "0.5", "--pipeline.model.sp.seed", "0",
            "blender-data", "--data", tiny_scene / "blender"]
    if server is not None:
        return server.call(args, {"TOY_FIELD_LOG": str(log)}, expect=expect)
    return run_env(args, dict(env, TOY_FIELD_LOG=str(log)), expect=expect)


TOY_METHODS = {"toy-method": "ToyModel", "toy-sdf": "ToySDFModel", "toy-blob": "ToyBlobModel"}
"""Plugin fields reading get_positions(), get_start_positions() (+ eikonal), get_gaussian_blob()."""


@pytest.fixture(scope="module")
def toy_server(toy):
    """``ns-eval`` and ``ns-render`` imported once, the plugin discovered (its path set); ``sp-train`` is
    imported by each child that runs it (so ``ns-eval`` runs as the real script would, without it)."""
    _, env = toy
    server = ForkServer(["ns-eval", "ns-render"], env)
    yield server
    server.close()


@pytest.fixture(scope="module", params=sorted(TOY_METHODS))
def toy_run(request, toy, toy_server, tiny_scene, tmp_path_factory):
    root, env = toy
    out = tmp_path_factory.mktemp(f"{request.param}-run")
    log = out / "train.jsonl"
    proc = sp_train_toy(request.param, env, out, tiny_scene, log, server=toy_server)
    (config,) = out.glob("**/config.yml")
    return request.param, config, log, proc, env


def test_sp_train_trains_a_plugin_method_with_its_field_perturbed_then_plain(toy_run):
    method, config, log, _, _ = toy_run
    training = [line for line in log_lines(log) if line["training"]]
    assert len(training) == STEPS, training  # one field query per step
    offsets = [line["offset"] for line in training]
    assert all(o > 1e-3 for o in offsets[:2]), offsets  # alpha 0.05: the field read moved positions
    assert all(o < 1e-6 for o in offsets[2:]), offsets  # alpha 0 from step 2 on: the plain positions
    assert config.parent.parent.name == method  # the run keeps the method's name (ns-eval looks it up)
    module = {"toy-method": "model", "toy-sdf": "sdf", "toy-blob": "blob"}[method]
    assert f"sp_plugins.nerfstudio.variants.SPModel__toyplugin_d{module}_d{TOY_METHODS[method]}" in config.read_text()


def test_ns_eval_and_ns_render_load_the_plugin_checkpoint_unperturbed(toy_run, toy_server, tmp_path):
    _, config, _, _, env = toy_run
    log = tmp_path / "eval.jsonl"
    env = {"TOY_FIELD_LOG": str(log)}
    toy_server.call([command("ns-eval"), "--load-config", config, "--output-path", tmp_path / "eval.json"], env)
    results = json.loads((tmp_path / "eval.json").read_text())["results"]
    assert math.isfinite(results["psnr"])
    toy_server.call([command("ns-render"), "dataset", "--load-config", config, "--split", "test", "--output-path",
                     tmp_path / "renders", "--rendered-output-names", "rgb", "--image-format", "png"], env)
    assert list((tmp_path / "renders").glob("**/*.png"))
    queries = log_lines(log)
    assert queries and not any(q["training"] for q in queries)
    assert max(q["offset"] for q in queries) < 1e-6  # evaluation and rendering see the plain field


def test_a_plugin_field_that_reads_positions_around_the_seam_is_refused_in_one_line(toy, tiny_scene, tmp_path):
    """Its positions come from the samples' metadata: it would train without SP, so it stops after
    the first step, naming the field class and what it read, before any checkpoint is written."""
    _, env = toy
    proc = sp_train_toy("toy-bypass", env, tmp_path, tiny_scene, tmp_path / "log.jsonl", expect=2)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "toyplugin.bypass.BypassField (model.field)" in lines[0], proc.stderr
    assert "read nothing of their frustums, never a position" in lines[0]
    assert not list(tmp_path.glob("**/*.ckpt"))


@pytest.mark.parametrize("method, says", [
    ("toy-download", ("DownloadModel of the plugin toyplugin", "failed while its model was built (populate_modules)",
                      "URLError", "Temporary failure in name resolution", "could not reach the network")),
    ("toy-nofield", ("SP cannot reach toyplugin.nofield.NoFieldModel", "no query would be perturbed")),
])
def test_a_plugin_model_that_cannot_be_built_or_reached_is_one_line_before_any_step(method, says, toy, toy_server, tiny_scene,
                                                                                   tmp_path):
    """A plugin that downloads weights while its model is built, run offline (its URLError was a
    traceback), and one with no field: each names the plugin, the step and the cause; no checkpoint."""
    from tests.helpers.errors import refused

    proc = sp_train_toy(method, None, tmp_path, tiny_scene, tmp_path / "log.jsonl", expect=2, server=toy_server)
    refused(proc, "sp-train", *says)
    assert not list(tmp_path.glob("**/*.ckpt")) and not log_lines(tmp_path / "log.jsonl")


def test_a_plugin_registers_its_sp_variant_with_one_with_sp_call(toy, tmp_path):
    """The plugin's own entry point ``sp-toy-method = with_sp(toy_method)`` reaches nerfstudio's list."""
    _, env = toy
    code = (
        "from nerfstudio.plugins.registry import discover_methods\n"
        "methods, descriptions = discover_methods()\n"
        "config = methods['sp-toy-method']\n"
        "print(type(config.pipeline.model).__name__, config.pipeline.model.sp.enabled, config.method_name)\n"
    )
    out = run_env([sys.executable, "-c", code], env).stdout.split()
    assert out[-3:] == ["SPModelConfig__toyplugin_dmodel_dToyModelConfig", "True", "sp-toy-method"]


REFUSED = {
    "splatfacto": "Gaussian splatting",
    "neus-hashgrid": "baseline of sp-neus-hashgrid",
    "relu-field-flat": "baseline of sp-relu-field",
    "zipnerf": "not installed",
    "instant-ngp": "nerfacc's CUDA kernels",
}


def test_sp_train_help_lists_every_method_and_refuses_the_unreachable_in_one_line(toy):
    _, env = toy
    help_text = run_env([command("sp-train"), "--help"], dict(env, COLUMNS="200")).stdout
    for method in ("nerfacto", "vanilla-nerf", "tensorf", "neus", "neus-facto", "mipnerf", "toy-method", "toy-sdf",
                   "sp-neus-hashgrid"):
        assert method in help_text, method
    proc = run_env([command("sp-train"), "splatfacto", "--max-num-iterations", "1"], env, expect=2)
    assert proc.stderr.strip().splitlines() == [f"sp-train: error: SP cannot be put on splatfacto: {_refusals()['splatfacto']}"]
    assert REFUSED["splatfacto"] in proc.stderr


def _refusals():
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    from sp_plugins.nerfstudio.registration import sp_methods

    return sp_methods(all_methods, all_descriptions)[2]


@pytest.fixture
def no_cuda(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_sp_train_offers_every_builtin_method_it_can_reach_and_says_why_not_for_the_rest(no_cuda):
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    from sp_plugins.nerfstudio.registration import sp_methods

    configs, _, refused = sp_methods(all_methods, all_descriptions)
    assert set(configs) | set(refused) == set(all_methods)
    for method, why in REFUSED.items():
        assert why in refused[method], (method, refused[method])
    for method in ("nerfacto", "nerfacto-big", "depth-nerfacto", "vanilla-nerf", "tensorf", "semantic-nerfw", "neus",
                   "neus-facto", "mipnerf"):
        model = configs[method].pipeline.model
        assert model.sp.enabled and type(model).__name__.startswith("SPModelConfig__"), method
        assert configs[method].method_name == all_methods[method].method_name  # ns-eval finds its data manager by it
    assert configs["sp-neus-hashgrid"].pipeline.model.sp.enabled
    # the paper's presets follow the host model: NeuS for surface models, MipNeRF's for mipnerf
    assert configs["neus-facto"].pipeline.model.sp.alpha0 == pytest.approx(0.013)
    assert configs["mipnerf"].pipeline.model.sp.alpha0 == pytest.approx(0.04)


# -- in-process ---------------------------------------------------------------------------------


@pytest.fixture
def toy_importable(toy, monkeypatch):
    root, _ = toy
    monkeypatch.syspath_prepend(str(root))
    return root


def test_with_sp_keeps_the_method_flags_and_adds_sp(toy_importable):
    from toyplugin.config import toy_method

    from sp_plugins.core import SPConfig
    from sp_plugins.nerfstudio import with_sp

    spec = with_sp(toy_method, SPConfig(alpha0=0.07))
    model = spec.config.pipeline.model
    host = toy_method.config.pipeline.model
    assert isinstance(model, type(host)) and model.sp.alpha0 == 0.07
    assert model.num_samples == host.num_samples and model.width == host.width
    assert spec.config.method_name == "sp-toy-method"
    assert "sp_alpha_grid" in spec.config.optimizers and "fields" in spec.config.optimizers
    assert toy_method.config.pipeline.model is host and not hasattr(host, "sp")  # the plugin's spec is untouched


def test_sp_variants_resolve_by_path_in_a_saved_config(toy_importable):
    """config.yml names the variants by path; a fresh process makes them again from the name."""
    from toyplugin.config import toy_method

    from sp_plugins.nerfstudio import variants, with_sp

    config = with_sp(toy_method).config
    loaded = yaml.load(yaml.dump(config), Loader=yaml.Loader)
    assert type(loaded.pipeline.model) is type(config.pipeline.model)
    assert loaded.pipeline.model._target is config.pipeline.model._target
    name = type(config.pipeline.model).__name__
    code = f"import sp_plugins.nerfstudio.variants as v; print(v.{name}.__mro__[2].__name__)"
    out = run_env([sys.executable, "-c", code], dict(ENV, PYTHONPATH=str(toy_importable))).stdout.split()[-1]
    assert out == "ToyModelConfig"
    with pytest.raises(AttributeError):
        variants.SPModel__not_da_dpath
    with pytest.raises(AttributeError):
        variants.SomethingElse


def test_a_field_built_through_a_module_object_is_reached(toy_importable, tiny_scene, tmp_path):
    """The seam is put on the field instances the model built, whatever name built them (a module
    object here, which no redirection of class names could reach)."""
    from toyplugin.config import toy_method
    from toyplugin.hidden import HiddenFieldModelConfig

    from sp_plugins.adapter.variants import convert
    from sp_plugins.nerfstudio import with_sp
    from sp_plugins.nerfstudio.runs import configure_run, train
    from sp_plugins.nerfstudio.seam import SeamField

    base = toy_method.config
    hidden = type(toy_method)(config=base, description="")
    hidden.config = type(base)(**{f: getattr(base, f) for f in ("method_name", "max_num_iterations", "mixed_precision", "optimizers")},
                               pipeline=type(base.pipeline)(datamanager=base.pipeline.datamanager,
                                                            model=convert(base.pipeline.model, HiddenFieldModelConfig)))
    config = with_sp(hidden).config
    config.pipeline.model.sp.end = 2  # alpha > 0 in step 0
    configure_run(config, tiny_scene / "blender", steps=3, output_dir=tmp_path)
    model = train(config).pipeline.model
    assert isinstance(model.field, SeamField) and model.field.sp is model.sp
    assert perturbed_calls(model) >= 2 and "origins" in model.field.sp_handle.reads


BUILTIN_TRAIN = ("nerfacto", "nerfacto-big", "nerfacto-huge", "vanilla-nerf", "tensorf", "phototourism", "dnerf", "mipnerf",
                 "neus", "neus-facto")
"""nerfstudio's methods that run on a CPU with the data a Blender scene gives (the NeuS family: the
SDFStudio layout of the same scene; depth-nerfacto, semantic-nerfw and generfacto need depth /
semantic data or downloaded models; instant-ngp needs CUDA)."""


@pytest.mark.parametrize("method", BUILTIN_TRAIN)
def test_sp_train_configs_of_builtin_methods_train_two_steps_with_sp_active(method, tiny_scene, tmp_path):
    import copy

    from tests.helpers.ns_configs import in_process_data, shrink_model
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    from sp_plugins.nerfstudio.registration import sp_methods
    from sp_plugins.nerfstudio.runs import configure_run, train

    config = copy.deepcopy(sp_methods({method: all_methods[method]}, all_descriptions)[0][method])
    shrink_model(config.pipeline.model)
    in_process_data(config)
    config.pipeline.model.sp.end = 2  # alpha > 0 in steps 0 and 1 of 3
    layout = "sdfstudio" if hasattr(config.pipeline.model, "sdf_field") else "blender"
    configure_run(config, tiny_scene / layout, steps=3, output_dir=tmp_path, rays_per_batch=32)
    trainer = train(config)
    model = trainer.pipeline.model
    fields = [f for f in sp_fields(model) if f.sp_handle.perturbed_calls]
    assert fields and perturbed_calls(model) >= 2, method  # a field was handed moved samples in both SP steps
    assert all("origins" in f.sp_handle.reads for f in fields), method  # ... and read them
    assert int(model.sp.step) >= 2 and model.sp.total_steps == 3
    assert list(config.get_checkpoint_dir().glob("*.ckpt"))


def test_depth_nerfacto_builds_with_sp_on_its_main_field():
    """depth-nerfacto needs depth images (or downloads a depth model) to train; its SP model builds
    and reaches the main field as nerfacto's does."""
    import copy

    import torch
    from nerfstudio.configs.method_configs import all_descriptions, all_methods
    from nerfstudio.data.scene_box import SceneBox

    from tests.helpers.ns_configs import shrink_model
    from sp_plugins.nerfstudio.registration import sp_methods

    model_config = copy.deepcopy(sp_methods({"depth-nerfacto": all_methods["depth-nerfacto"]}, all_descriptions)[0]["depth-nerfacto"].pipeline.model)
    shrink_model(model_config)
    model = model_config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2, metadata={}, device="cpu")
    from sp_plugins.nerfstudio.seam import host_name

    reached = [host_name(f).rsplit(".", 1)[-1] for f in sp_fields(model)]
    assert "NerfactoField" in reached and all(f.sp is model.sp for f in sp_fields(model))


def test_neus_keeps_its_background_plain_and_its_sdf_field_carries_the_seam():
    """The paper perturbs the SDF field only: a surface model's background (outside the SDF's
    sphere) is listed in PLAIN_FIELDS; nerfstudio's own SDFField is built on our torch hash grid
    without tcnn, for that build only."""
    import torch
    from tests.helpers.ns_configs import shrink_model, sp_train_config
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.fields.sdf_field import SDFField
    from nerfstudio.fields.vanilla_nerf_field import NeRFField

    from sp_plugins.nerfstudio.seam import SeamField

    model_config = sp_train_config("neus").pipeline.model
    shrink_model(model_config)
    model_config.background_model = "mlp"
    model = model_config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2, metadata={}, device="cpu")
    assert isinstance(model.field, SeamField) and isinstance(model.field, SDFField)
    assert isinstance(model.field_background, NeRFField) and not isinstance(model.field_background, SeamField)
    assert model.sp.config.alpha0 == 0.013  # the NeuS preset
