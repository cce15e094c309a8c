"""nerfbaselines' own commands on our methods, run as a user types them, at a tiny budget.

One module fixture trains ``sp-nerfacto`` three steps through ``nerfbaselines train --backend python``
on a bundled scene (Blender layout, loaded by nerfbaselines' own Blender loader through the
``nb-info.json`` sp-scene writes); ``render``, ``evaluate`` and ``generate-dataset-results`` run on
what it wrote. An SDF method trains on the SDFStudio layout (our loader) and gets the dataset's box.
A Blender-format folder of one's own (no ``nb-info.json``) trains through our Blender-layout loader.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.ns_commands import ENV, command

STEPS = 3
BUDGET = ["--set", "machine.device_type=cpu", "--set", f"max_num_iterations={STEPS}",
          "--set", "pipeline.datamanager.train_num_rays_per_batch=32",
          "--set", "pipeline.model.eval_num_rays_per_chunk=512"]
NERFACTO = ["--set", "pipeline.model.num_nerf_samples_per_ray=8", "--set", "pipeline.model.num_proposal_samples_per_ray=8,8",
            "--set", "pipeline.model.log2_hashmap_size=12", "--set", "pipeline.model.max_res=64",
            "--set", "pipeline.model.hidden_dim=16"]
SDF = ["--set", "pipeline.model.num_samples=16", "--set", "pipeline.model.num_samples_importance=8",
       "--set", "pipeline.model.num_up_sample_steps=1", "--set", "pipeline.model.num_samples_outside=8",
       "--set", "pipeline.model.sdf_field.log2_hashmap_size=12", "--set", "pipeline.model.sdf_field.max_res=64"]
SKIPPED = "LPIPS skipped (NaN): the alex backbone weights are not in the torch hub cache"


def nb(*args: str, env=None, expect: int = 0, timeout: int = 600, server=None) -> subprocess.CompletedProcess:
    """``nerfbaselines ARGS`` as typed: the real script, or (``server``) forked from one interpreter that
    imported nerfbaselines and nerfstudio once (tests/helpers/forkserver.py)."""
    if server is not None:
        return server.call([command("nerfbaselines"), *args], env=env, expect=expect)
    proc = subprocess.run([command("nerfbaselines"), *args], env=env or ENV, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == expect, f"nerfbaselines {' '.join(args)}\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    return proc


@pytest.fixture(scope="module")
def nb_server():
    """The fork server with nerfbaselines' commands, nerfstudio and our wrapper imported once: render,
    evaluate, the results table, the refused --set and the SDF run each skip 10-20 s of imports (the
    training fixture runs the real script)."""
    from tests.helpers.forkserver import ForkServer

    server = ForkServer(["nerfbaselines", "nerfbaselines.cli._train", "nerfbaselines.cli._render", "nerfbaselines.cli._evaluate",
                         "nerfbaselines.cli._generate_dataset_results", "sp_plugins.nerfbaselines.method",
                         "nerfstudio.configs.method_configs"], ENV)
    yield server
    server.close()


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("nb") / "my-scene"
    subprocess.run([command("sp-scene"), "spot", str(root), "--resolution", "32", "--views", "8", "--test-views", "2",
                    "--quiet"], env=ENV, check=True, capture_output=True, timeout=300)
    return root


@pytest.fixture(scope="module")
def trained(scene) -> tuple:
    out = scene.parent / "sp-nerfacto"
    proc = nb("train", "--method", "sp-nerfacto", "--backend", "python", "--data", str(scene / "blender"),
              "--output", str(out), *BUDGET, *NERFACTO)
    return out, proc


def our_psnr(predictions: Path) -> float:
    """Our metric code (sp_plugins.tasks.image.psnr) on the images the protocol compares: the rendered
    and ground-truth PNGs composited on white (the dataset's background) and cut to 8 bits as
    nerfbaselines does (truncation), averaged over the test images."""
    import imageio.v2 as imageio

    from sp_plugins.tasks.image import psnr

    def srgb(path: Path) -> np.ndarray:
        image = imageio.imread(path).astype(np.float32) / np.float32(255.0)
        if image.shape[-1] == 4:
            image = image[..., :3] * image[..., 3:] + (1.0 - image[..., 3:])
        return np.floor(np.clip(image * np.float32(255.0), 0, 255)) / 255.0

    preds = sorted((predictions / "color").rglob("*.png"))
    assert preds, f"no rendered images under {predictions}"
    return float(np.mean([psnr(srgb(p), srgb(predictions / "gt-color" / p.relative_to(predictions / "color")))
                          for p in preds]))


def untar(archive: Path) -> Path:
    folder = archive.with_suffix("").with_suffix("")
    with tarfile.open(archive) as tar:
        tar.extractall(folder, filter="data")
    return folder


def test_train_writes_checkpoint_renders_results_and_one_lpips_line(trained):
    out, proc = trained
    checkpoint = out / f"checkpoint-{STEPS}"
    assert list((checkpoint / "nerfstudio_models").glob("step-*.ckpt")), "no checkpoint"
    assert "SP" in (checkpoint / "config.yml").read_text() and "enabled: true" in (checkpoint / "config.yml").read_text()
    assert not (checkpoint / "sp-scene-box.json").exists()  # a radiance method keeps nerfstudio's box, as in ns-train
    assert (out / f"predictions-{STEPS}.tar.gz").is_file()
    results = json.loads((out / f"results-{STEPS}.json").read_text())
    assert math.isfinite(results["metrics"]["psnr"]) and math.isfinite(results["metrics"]["ssim"])
    assert math.isnan(results["metrics"]["lpips"])  # no weights here: skipped, not downloaded
    assert results["render_dataset_metadata"]["id"] == "sp-scene" and results["evaluation_protocol"] == "sp-scene"
    lines = [line for line in proc.stderr.splitlines() if "LPIPS" in line and "skipped" in line]
    assert len(lines) == 1 and "alexnet-owt-7be5be79.pth" in lines[0], lines


def test_render_and_evaluate_give_our_psnr_and_lpips_with_weights(trained, tmp_path, nb_server):
    """``render`` from the checkpoint, then ``evaluate`` with (stand-in) LPIPS weights in the torch hub
    cache: LPIPS is computed, and PSNR is what our own metric code gives on the same images."""
    import torch
    import torchvision

    out, _ = trained
    hub = tmp_path / "torch"
    (hub / "hub" / "checkpoints").mkdir(parents=True)
    net = torchvision.models.alexnet()  # small stand-in: real features, the classifier as one broadcast value
    state = {k: (v if k.startswith("features") else torch.zeros(1).expand(v.shape)) for k, v in net.state_dict().items()}
    torch.save(state, hub / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth")
    env = {"TORCH_HOME": str(hub)}
    renders = tmp_path / "renders"
    nb("render", "--checkpoint", str(out / f"checkpoint-{STEPS}"), "--data", str(out.parent / "my-scene" / "blender"),
       "--output", str(renders), "--backend", "python", env=env, server=nb_server)
    rendered = sorted((renders / "color").rglob("*.png"))
    assert len(rendered) == 2
    # the reloaded model renders what the trained one rendered at its last step (train's predictions):
    # nerfacto's proposal anneal is step state outside the state dict, restored by our wrapper on load
    import imageio.v2 as imageio

    trained_renders = untar(out / f"predictions-{STEPS}.tar.gz")
    for path in rendered:
        again = imageio.imread(trained_renders / "color" / path.relative_to(renders / "color")).astype(int)
        assert np.abs(imageio.imread(path).astype(int) - again).max() <= 1, path
    proc = nb("evaluate", str(renders), "-o", str(tmp_path / "results.json"), env=env, server=nb_server)
    metrics = json.loads((tmp_path / "results.json").read_text())["metrics"]
    assert math.isfinite(metrics["lpips"]) and "skipped" not in proc.stderr
    assert abs(metrics["psnr"] - our_psnr(renders)) < 1e-3, metrics


def test_results_table_from_nerfbaselines_tooling(trained, nb_server):
    out, _ = trained
    proc = nb("generate-dataset-results", "--results", str(out), "--dataset", "sp-scene", "--scenes", "spot", server=nb_server)
    assert "sp-nerfacto" in proc.stdout and "PSNR" in proc.stdout, proc.stdout


def test_unknown_set_key_is_one_line_with_the_keys_that_exist(scene, tmp_path, nb_server):
    proc = nb("train", "--method", "sp-nerfacto", "--backend", "python", "--data", str(scene / "blender"),
              "--output", str(tmp_path / "run"), *BUDGET, "--set", "pipeline.model.sp.alpha00=0.1", expect=2,
              server=nb_server)
    (line,) = [line for line in proc.stderr.splitlines() if "error" in line]
    assert "pipeline.model.sp.alpha00" in line and "alpha0" in line and "enabled" in line, line
    assert "Traceback" not in proc.stderr


def test_sdf_method_gets_the_dataset_box_and_scores_as_ours(scene, nb_server):
    """sp-neus-hashgrid on the SDFStudio layout (our loader): the box is meta_data.json's, not
    nerfbaselines' fixed one, and the results nerfbaselines wrote match our PSNR on its renders."""
    out = scene.parent / "sp-neus-hashgrid"
    proc = nb("train", "--method", "sp-neus-hashgrid", "--backend", "python", "--data", str(scene / "sdfstudio"),
              "--output", str(out), *BUDGET, *SDF, server=nb_server)
    box = json.loads((scene / "sdfstudio" / "meta_data.json").read_text())["scene_box"]["aabb"]
    assert f"sp-neus-hashgrid: scene box {box} from the dataset" in proc.stderr, proc.stderr[-3000:]
    assert json.loads((out / f"checkpoint-{STEPS}" / "sp-scene-box.json").read_text())["aabb"] == box
    results = json.loads((out / f"results-{STEPS}.json").read_text())["metrics"]
    assert abs(results["psnr"] - our_psnr(untar(out / f"predictions-{STEPS}.tar.gz"))) < 1e-3, results


def own_blender_folder(blender: Path, root: Path) -> Path:
    """What a user has: the transforms files (without ``w`` / ``h``, as nerf_synthetic's) and the images
    of an sp-scene Blender folder, no ``nb-info.json`` nor anything else sp-scene writes."""
    root.mkdir()
    for split in ("train", "val", "test"):
        meta = json.loads((blender / f"transforms_{split}.json").read_text())
        (root / f"transforms_{split}.json").write_text(json.dumps({k: v for k, v in meta.items() if k not in ("w", "h")}))
        shutil.copytree(blender / split, root / split)
    return root


def test_own_blender_folder_trains_as_blender_data_with_sp_on(scene, tmp_path, nb_server):
    """``nerfbaselines train --data DIR`` on a Blender-format folder: our loader finds it, our preset puts
    it on nerfstudio's blender-data parser (as ``ns-train ... blender-data --data DIR``), and what the run
    did about SP is in the checkpoint's and the results' hparams."""
    mine = own_blender_folder(scene / "blender", tmp_path / "my-object")
    out = tmp_path / "nerfacto+sp"
    nb("train", "--method", "nerfacto+sp", "--backend", "python", "--data", str(mine), "--output", str(out),
       *BUDGET, *NERFACTO, server=nb_server)
    checkpoint = out / f"checkpoint-{STEPS}"
    info = json.loads((checkpoint / "nb-info.json").read_text())
    assert info["applied_presets"] == ["blender-layout"] and info["dataset_metadata"]["layout"] == "blender"
    assert "BlenderDataParserConfig" in (checkpoint / "config.yml").read_text()
    results = json.loads((out / f"results-{STEPS}.json").read_text())
    assert math.isfinite(results["metrics"]["psnr"])
    for hparams in (info["hparams"], results["nb_info"]["hparams"]):
        assert hparams["sp_run.enabled"] is True and hparams["sp_run.fields"] and hparams["sp_run.alpha0"] > 0
