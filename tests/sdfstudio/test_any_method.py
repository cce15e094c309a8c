"""SP on any sdfstudio SDF method: every method sdfstudio registers is either
offered as ``sp-<method>`` (and trains with SP active) or refused in one line that says why.

README's table of sdfstudio's methods is the generated one (``python -m sp_plugins.method_table``).
"""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.errors import refused
from tests.helpers.sdf_configs import BIN, env, pairs_file, run, run_dir, tiny_config, train_args, train_in_process

pytestmark = pytest.mark.usefixtures("patched")

TRAINS = [
    "neus", "neus-facto", "neus-facto-angelo", "neus-facto-bigmlp", "neus-acc", "geo-neus", "mono-neus",
    "volsdf", "geo-volsdf", "monosdf", "unisurf", "geo-unisurf", "mono-unisurf",
    "bakedsdf", "bakedsdf-mlp", "neuralangelo", "bakedangelo",
]
"""sdfstudio (370902a) SDF methods whose SP variant trains here (CPU)."""
CUDA_ONLY = {
    "neusW": "offered; not trained here: its NeuralReconW sampler ray-marches with nerfacc's CUDA kernels and reads "
             "the coarse occupancy grid of the heritage data parser (checked: the SP model builds with SP attached)",
}
REFUSED = ["dto", "nerfacto", "instant-ngp", "mipnerf", "semantic-nerfw", "vanilla-nerf", "tensorf", "dnerf", "phototourism"]
CONTROLS_ANGELO = {"neuralangelo", "bakedangelo", "neus-facto-angelo"}
"""Host configs that enable progressive hash encoding: the Neuralangelo preset, coarse-to-fine replaced."""



def host_methods():
    import nerfstudio.configs.method_configs as host

    return {name: config for name, config in host.method_configs.items() if not hasattr(config.pipeline.model, "sp")}


def test_every_host_method_is_offered_or_refused():
    import nerfstudio.configs.method_configs as host
    import scripts.train

    from sp_plugins.sdfstudio.registration import REFUSED as refused

    assert set(host_methods()) == set(TRAINS) | set(CUDA_ONLY) | set(REFUSED), "sdfstudio's method list changed"
    for method in [*TRAINS, *CUDA_ONLY]:
        config = host.method_configs[f"sp-{method}"]
        assert config.method_name == f"sp-{method}" and config.pipeline.model.sp.enabled
        assert f"sp-{method}" not in refused
    for method in REFUSED:
        assert f"sp-{method}" not in host.method_configs and refused[f"sp-{method}"]
    assert "DtoOModel" in refused["sp-dto"] and "NerfactoModel" in refused["sp-nerfacto"]
    assert scripts.train.AnnotatedBaseConfigUnion is host.AnnotatedBaseConfigUnion  # ns-train sees them


@pytest.mark.parametrize("method", [*TRAINS, *CUDA_ONLY])
def test_presets_and_the_one_seam(method):
    """The model config is the SP variant of the host's own class, the field SeamSDFFieldConfig, and
    the preset the host's coarse-to-fine decides."""
    import nerfstudio.configs.method_configs as host

    from sp_plugins.adapter import presets
    from sp_plugins.sdfstudio.seam import SeamSDFFieldConfig
    from sp_plugins.sdfstudio.variants import variant

    ours, theirs = host.method_configs[f"sp-{method}"].pipeline.model, host.method_configs[method].pipeline.model
    assert type(ours) is variant("ModelConfig", type(theirs)) and ours._target is variant("Model", theirs._target)
    assert type(ours.sdf_field) is SeamSDFFieldConfig
    angelo = method in CONTROLS_ANGELO
    assert theirs_enables(theirs) == angelo
    expected = presets.NEURALANGELO if angelo else presets.NEUS
    assert ours.sp == expected
    if angelo:
        assert not ours.enable_progressive_hash_encoding and not ours.enable_numerical_gradients_schedule
        assert ours.sdf_field.fd_step is not None


def theirs_enables(model) -> bool:
    return getattr(model, "enable_progressive_hash_encoding", False) is True


@pytest.fixture(scope="module")
def scene_with_pairs(sdf_scene) -> Path:
    """The tiny scene plus a pairs.txt (GeoNeuS patch warping reads source views)."""
    frames = json.loads((sdf_scene / "meta_data.json").read_text())["frames"]
    pairs_file(sdf_scene, len(frames))
    return sdf_scene


@pytest.mark.parametrize("method", TRAINS)
def test_sp_method_trains_two_steps_with_sp_active(method, scene_with_pairs, tmp_path):
    import nerfstudio.configs.method_configs as host
    import torch

    from sp_plugins.sdfstudio.seam import SeamSDFField

    torch.manual_seed(0)
    config = tiny_config(host.method_configs[f"sp-{method}"], scene_with_pairs, tmp_path, steps=3)
    # end 1.0: alpha > 0 at steps 0 and 1, 0 at the last step (SP ends there at the latest)
    config.pipeline.model.sp = dataclasses.replace(config.pipeline.model.sp, end=1.0)
    trainer = train_in_process(config)
    model = trainer.pipeline.model
    assert isinstance(model.field, SeamSDFField) and model.field.sp is model.sp
    calls = model.field.sp_handle.perturbed_calls
    assert calls >= 2, f"SP perturbed {calls} field queries in the 2 steps with alpha > 0"
    assert model.sp_run.reach_checked and float(model.field.sp_handle.first_move) > 0  # the model's own check ran
    assert int(model.sp.step) == 2 and int(model.sp.total_steps) == 3 and model.sp.alpha == 0
    assert (tmp_path / "exp" / f"sp-{method}" / "run" / "sdfstudio_models" / "step-000000002.ckpt").is_file()


@pytest.mark.parametrize("method", ["neus", "neuralangelo"])
def test_the_fields_queries_move_against_the_plain_positions(method, scene_with_pairs, tmp_path):
    """Measured where the field reads, not counted: every training query the SDF network gets is
    the plain contracted position moved by noise of std alpha (and Neuralangelo's six stencil points
    share that one offset). Counting calls passed with the contraction returning its input."""
    import nerfstudio.configs.method_configs as host
    import torch

    torch.manual_seed(0)
    config = tiny_config(host.method_configs[f"sp-{method}"], scene_with_pairs, tmp_path, steps=3)
    config.pipeline.model.sp = dataclasses.replace(config.pipeline.model.sp, end=1.0)
    events = []  # in call order: ("contract", positions, alpha) and ("geo", network input)
    trainer = None

    def record_contraction(module, args, output):
        if module.training and trainer.pipeline.model.sp.active:
            events.append(("contract", args[0].detach().clone(), trainer.pipeline.model.sp.alpha))

    from nerfstudio.engine.trainer import Trainer

    from sp_plugins.patches.sdfstudio_cuda import cpu_meaning

    with cpu_meaning():
        trainer = Trainer(config, local_rank=0, world_size=0)
        trainer.setup()
        field = trainer.pipeline.model.field
        field.spatial_distortion.register_forward_hook(record_contraction)
        network = field.forward_geonetwork

        def record_network(inputs):  # a spy: the field's own network runs on what it was handed
            events.append(("geo", inputs.detach().clone(), None))
            return network(inputs)

        field.forward_geonetwork = record_network
        trainer.train()
    inner = field.spatial_distortion.inner
    checked = 0
    for i, (kind, positions, alpha) in enumerate(events):
        if kind != "contract":
            continue
        queried = next(t for k, t, _ in events[i + 1:] if k == "geo")
        plain = positions if inner is None else inner(positions)
        if queried.shape[0] == 6 * plain.shape[0]:  # gradient(): the stencil, centred on the moved point
            stencil = queried.view(6, *plain.shape)
            queried = (stencil[0] + stencil[1]) / 2
        else:
            assert queried.shape == plain.shape
            following = [t for k, t, _ in events[i + 2:i + 3] if k == "geo"]
            if method == "neuralangelo" and following:  # the stencil around the moved query: one offset
                stencil = following[0].view(6, *plain.shape)
                torch.testing.assert_close((stencil[0] + stencil[1]) / 2, queried, rtol=0, atol=1e-5)
        move = queried - plain
        inside = (plain.abs() < 2 - 4 * alpha).all(-1)  # away from the walls the reflection leaves alone
        assert float(move.abs().max()) > 0, f"the field was queried at the plain positions (call {i}, alpha {alpha:g})"
        assert float(move[inside].std()) == pytest.approx(alpha, rel=0.25), (float(move[inside].std()), alpha)
        checked += 1
    assert checked >= 2  # the two steps with alpha > 0
    assert float(field.sp_handle.first_move) > 0


def test_a_field_that_moved_nothing_is_refused_in_one_line():
    """The product's own reach check (run after the first step with alpha > 0): a handle that
    recorded no perturbed query, or a first move of 0, stops the run with one line."""
    import torch
    from torch import nn

    from sp_plugins.adapter.errors import InputError
    from sp_plugins.adapter.field import PreconditionerHandle
    from sp_plugins.sdfstudio.seam import check_reached

    model = nn.Module()
    model.field = nn.Module()
    model.field.sp_handle = PreconditionerHandle(None)
    with pytest.raises(InputError, match="SP reached no SDF query of NeuSModel in training step 0"):
        check_reached(model, "NeuSModel", 0)
    model.field.sp_handle.perturbed_calls, model.field.sp_handle.first_move = 3, torch.tensor(0.0)
    with pytest.raises(InputError, match="moved no position .largest move 0.: the perturbation is not applied"):
        check_reached(model, "NeuSModel", 0)
    model.field.sp_handle.first_move = torch.tensor(0.01)
    check_reached(model, "NeuSModel", 0)


@pytest.mark.parametrize("method", sorted(CUDA_ONLY))
def test_cuda_only_sp_method_builds_with_sp(method, sdf_scene, tmp_path, monkeypatch):
    """neusW needs the heritage parser's coarse grid (given here) and CUDA to sample: its SP model
    is built (SP attached to its SDF field); training runs only where nerfacc has CUDA."""
    import nerfstudio.configs.method_configs as host
    import torch
    from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudio
    from nerfstudio.engine.trainer import Trainer

    from sp_plugins.sdfstudio.seam import SeamSDFField

    plain = SDFStudio._generate_dataparser_outputs

    def with_coarse_grid(self, split="train"):
        outputs = plain(self, split)
        outputs.scene_box.coarse_binary_gird = torch.ones(32**3, dtype=torch.bool)
        return outputs

    monkeypatch.setattr(SDFStudio, "_generate_dataparser_outputs", with_coarse_grid)
    trainer = Trainer(tiny_config(host.method_configs[f"sp-{method}"], sdf_scene, tmp_path), local_rank=0, world_size=0)
    trainer.setup()
    model = trainer.pipeline.model
    assert isinstance(model.field, SeamSDFField) and model.field.sp is model.sp


def test_a_generic_method_end_to_end_and_its_config_loads_by_path(sdf_scene, tmp_path):
    """sp-volsdf through sp-sdfstudio-train; its config.yml names the variant classes by path and
    loads with sdfstudio's eval_setup in a fresh process (nothing registered there)."""
    out = tmp_path / "out"
    run(["sp-sdfstudio-train", *train_args("sp-volsdf", "volsdf", sdf_scene, out, 2)], cwd=tmp_path)
    run_path = run_dir(out, "sp-volsdf")
    text = (run_path / "config.yml").read_text()
    assert "sp_plugins.sdfstudio.variants.SPModelConfig__nerfstudio_dmodels_dvolsdf_dVolSDFModelConfig" in text
    assert "sp_plugins.sdfstudio.variants.SPModel__nerfstudio_dmodels_dvolsdf_dVolSDFModel" in text
    code = (
        "import sys; from pathlib import Path\n"
        "from nerfstudio.utils.eval_utils import eval_setup\n"
        "assert 'sp_plugins.sdfstudio.variants' not in sys.modules\n"
        f"_, pipeline, ckpt = eval_setup(Path({str(run_path / 'config.yml')!r}))\n"
        "model = pipeline.model\n"
        "print(type(model).__module__, type(model).__name__, type(model.field).__name__, int(model.sp.step), model.config.sp.enabled)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().splitlines()[-1] == (
        "sp_plugins.sdfstudio.variants SPModel__nerfstudio_dmodels_dvolsdf_dVolSDFModel SeamSDFField 1 True"
    )


def test_a_method_without_sdf_field_is_refused_in_one_line(tmp_path):
    proc = run(["sp-sdfstudio-train", "sp-nerfacto", "--machine.num-gpus", "0"], cwd=tmp_path, expect=2)
    last = refused(proc, "sp-sdfstudio-train", others=True)
    assert last.startswith("sp-sdfstudio-train: error: SP cannot be put on nerfacto: its model (NerfactoModel) has no SDF field")


def test_more_than_one_draw_is_refused_in_one_line_before_anything_is_written(tmp_path):
    """``--pipeline.model.sp.num-samples 2`` cannot act in sdfstudio (its seam perturbs each query once):
    ``sp-sdfstudio-train`` refuses it in one line, exit status 2, before a run folder exists (it was a
    traceback from inside the trainer, after ``config.yml``)."""
    proc = run(["sp-sdfstudio-train", "sp-neus", "--machine.num-gpus", "0", "--pipeline.model.sp.num-samples", "2",
                "sdfstudio-data", "--data", str(tmp_path)], cwd=tmp_path, expect=2)
    last = refused(proc, "sp-sdfstudio-train", others=True)
    assert last.startswith("sp-sdfstudio-train: error: --pipeline.model.sp.num-samples 2 cannot apply to sdfstudio"), last
    assert not (tmp_path / "outputs").exists()


def test_a_missing_data_folder_or_index_file_is_one_line_before_anything_is_written(tmp_path):
    """``--data`` that is not a scene: one line naming the path and the layout (it was sdfstudio's
    ``FileNotFoundError`` traceback, after the run folder was made)."""
    (tmp_path / "empty").mkdir()
    for data, says in [(tmp_path / "none", "data folder not found"), (tmp_path / "empty", "meta_data.json: file not found")]:
        proc = run(["sp-sdfstudio-train", "sp-neus", "--machine.num-gpus", "0", "sdfstudio-data", "--data", str(data)],
                   cwd=tmp_path, expect=2)
        last = refused(proc, "sp-sdfstudio-train", others=True)
        assert says in last and str(data) in last, last
    assert not (tmp_path / "outputs").exists()


def listed_methods(help_text: str) -> set:
    """The subcommand choices of a tyro usage line (``{a,b,...}``, wrapped anywhere)."""
    choices = re.search(r"\{([^}]*)\}", help_text)
    assert choices, help_text[:500]
    return set(re.sub(r"\s+", "", choices.group(1)).split(","))


def test_help_of_both_commands_lists_the_generic_methods(capsys, tmp_path):
    from sp_plugins.sdfstudio import cli

    offered = {f"sp-{m}" for m in [*TRAINS, *CUDA_ONLY]}
    with pytest.raises(SystemExit) as exit_info:
        cli.train(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    listed = listed_methods(out)
    assert offered <= listed and not {f"sp-{m}" for m in REFUSED} & listed
    assert "Not offered" in out and "sp-nerfacto" in out
    proc = subprocess.run([str(BIN / "ns-train"), "--help"], cwd=tmp_path, env=env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-1000:]
    assert offered <= listed_methods(proc.stdout), "sdfstudio's ns-train (opt-in hook) does not list them"


def test_the_readme_table_is_the_generated_one():
    """The sdfstudio method table (docs/guides/sdfstudio.md) is ``sp_plugins.method_table``'s, and what it offers and refuses
    is what the tests above train, build and refuse."""
    from sp_plugins import method_table

    outcomes = method_table.sdfstudio_outcomes()
    assert set(outcomes) == set(host_methods()), "sdfstudio's method list changed"
    assert {m for m, (order, _) in outcomes.items() if order == 0} == set(TRAINS) | set(CUDA_ONLY)
    assert {m for m, (order, _) in outcomes.items() if order == 1} == set(REFUSED)
    begin, end = method_table.markers("sdfstudio")
    text = method_table.page("sdfstudio").read_text()
    assert begin in text and end in text, "docs/guides/sdfstudio.md has lost the sdfstudio method table's markers"
    assert text[text.index(begin): text.index(end) + len(end)] == method_table.table("sdfstudio", outcomes), (
        "the sdfstudio method table in docs/guides/sdfstudio.md is out of date: run python -m sp_plugins.method_table --write in sdfstudio's environment"
    )
    after = text.partition(end)[2][:400]
    assert all(f"`{m}`" in after for m in CUDA_ONLY), "the sentence under the table names other untrained methods"
