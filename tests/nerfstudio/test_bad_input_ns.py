"""Bad input to the nerfstudio commands on our methods: each kind answered by the command
a user runs as one line naming the file or flag and what was expected, exit status 2, nothing
written or overwritten.

Every command runs as its own process. To keep this within budget (an ``ns-*`` start-up imports
nerfstudio and every method: 20-30 s here), the commands run in children of one fork server that
imported them once (``tests/helpers/forkserver.py``: the console script's entry point, ``sys.argv`` and the
interpreter's handling of an uncaught exception and of ``SystemExit``). The truncated checkpoint
under ``ns-eval`` runs the real console script instead, so the one-line report is also shown from a
real interpreter's top level (our exception hook ends with ``SystemExit(2)``). The runs these
commands load are written as ``ns-train`` leaves them (config.yml, nerfstudio_models/) without
training: every case fails before a model's weights would be read.

The ``typed-*`` cases are commands as a new user types them, with the host's defaults
(no ``--output-dir``: each runs in a folder of its own, which must stay empty; no ``--vis``): no
device flag on a CPU-only machine, no dataparser named, SP options that cannot act, ``sp-train`` on
a host method whose worker-process data manager hung on a damaged image, and the host's ``wandb``
default without an account.

Out of reach for ``ns-eval`` (nerfstudio reads the file before any of our code runs; see the README's
troubleshooting table): a missing ``--load-config`` and a ``config.yml`` naming a class this
installation lacks; ``sp-export-mesh`` answers both, tested here.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import torch
import yaml

from tests.helpers import errors
from tests.helpers.fs_faults import listing, make_read_only, undo_read_only
from tests.helpers.ns_commands import ENV, RUN_FLAGS, SDF_FLAGS, command
from tests.helpers.ns_configs import tiny_sdf_config

METHOD = "sp-neus-hashgrid"
TRAIN = [*RUN_FLAGS, *SDF_FLAGS, "--max-num-iterations", "2", "--steps-per-save", "2"]


def one_line_error(result: dict, *says: str, prog: str) -> str:
    """Exit status 2, a last stderr line ``<prog>: error: ...`` holding every word of ``says`` (the
    only error line), no traceback."""
    return errors.one_line_error(result["rc"], result["stderr"], prog, *says, stdout=result["stdout"], name=result["name"])


def saved_run(scene: Path, dest: Path, edit=None, checkpoint: str = "truncated") -> Path:
    """The folder ``ns-train`` would leave for a tiny run of the method on ``scene`` (blender layout),
    without training: its config.yml (``edit`` applied) and a step-1 checkpoint that is a real
    PyTorch file, cut in half unless ``checkpoint`` is "intact". Returns the config.yml."""
    config = tiny_sdf_config(METHOD, scene, dest, layout="blender", steps=2)
    if edit is not None:
        edit(config)
    base = Path(config.get_base_dir())
    (base / "nerfstudio_models").mkdir(parents=True)
    (base / "config.yml").write_text(yaml.dump(config))
    ckpt = base / "nerfstudio_models" / "step-000000001.ckpt"
    torch.save({"step": 1, "pipeline": {"_model.field.weight": torch.zeros(4096)}, "optimizers": {}, "scalers": {}}, ckpt)
    if checkpoint != "intact":
        truncate(ckpt)
    return base / "config.yml"


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.fixture(scope="module")
def cases(tiny_scene, ns_server, tmp_path_factory):
    """Every bad input, prepared, run in one batch (two at a time) while the real ``ns-eval`` runs
    one case; ``name -> (result, before, after)``, where before / after list the folder the command
    must leave alone."""
    root = tmp_path_factory.mktemp("bad")
    scene = tiny_scene / "blender"

    truncated = saved_run(tiny_scene, root / "truncated")
    ckpt = truncated.parent / "nerfstudio_models" / "step-000000001.ckpt"

    def retire(cfg):  # a config.yml from another version: a setting this one does not know
        vars(cfg.pipeline.model.sp)["retired_option"] = 1

    other_version = saved_run(tiny_scene, root / "other-version", retire, checkpoint="intact")
    missing_class = saved_run(tiny_scene, root / "missing-class", checkpoint="intact")
    text = missing_class.read_text()
    assert "sp_plugins.nerfstudio.neus.SPNeuSModelConfig" in text
    missing_class.write_text(text.replace("sp_plugins.nerfstudio.neus.SPNeuSModelConfig", "sp_plugins.nerfstudio.retired.SPNeuSModelConfig"))
    intact = saved_run(tiny_scene, root / "intact", checkpoint="intact")

    colmap = root / "colmap-capture"
    (colmap / "sparse" / "0").mkdir(parents=True)
    (colmap / "sparse" / "0" / "cameras.bin").write_bytes(b"\0" * 16)
    (colmap / "images").mkdir()
    capture = root / "ns-capture"
    capture.mkdir()
    (capture / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": []}))
    damaged = root / "damaged-scene"
    shutil.copytree(scene, damaged)
    truncate(damaged / "train" / "r_2.png")

    read_only = root / "read-only"
    read_only_ok = make_read_only(read_only)

    def train(name, data_args, *extra, fsize=None):
        out = root / f"out-{name}"
        case = {"name": name, "script": "ns-train", "args": [METHOD, *TRAIN, "--output-dir", str(out), *extra, *data_args]}
        if fsize is not None:
            case["fsize"] = fsize
        return case, out

    blender = ["blender-data", "--data", str(scene)]

    def typed(name, script, *args, timeout=None, env=None):
        """A command as a user types it (the host's defaults: no --output-dir, so it runs in a folder
        of its own and writes ./outputs there), with a time limit where the old code hung."""
        cwd = root / f"typed-{name}"
        cwd.mkdir()
        case = {"script": script, "args": list(args), "cwd": str(cwd), "env": env or {}}
        if timeout is not None:
            case["timeout"] = timeout
        return case, cwd

    cpu = ["--machine.device-type", "cpu"]
    plan = {
        # the commands users reach for first
        "typed-neus-no-device": typed("neus-no-device", "ns-train", "sp-neus", "--data", str(tiny_scene / "sdfstudio")),
        "typed-sp-train-no-device": typed("sp-train-no-device", "sp-train", "nerfacto", "--data", str(scene)),
        "typed-nerfacto-no-dataparser": typed("nerfacto-no-dataparser", "ns-train", "sp-nerfacto", *cpu, "--data", str(scene)),
        "typed-tensorf-alpha-grid": typed("tensorf-alpha-grid", "ns-train", "sp-tensorf", *cpu,
                                          "--pipeline.model.sp.alpha-grid", "True", *blender),
        "typed-nerfacto-reflect": typed("nerfacto-reflect", "ns-train", "sp-nerfacto", *cpu, "--pipeline.model.sp.boundary",
                                        "reflect", *blender, timeout=300),
        "typed-num-samples-sp-off": typed("num-samples-sp-off", "ns-train", "sp-nerfacto", *cpu, "--pipeline.model.sp.enabled",
                                          "False", "--pipeline.model.sp.num-samples", "2", *blender),
        "typed-sp-train-damaged-image": typed("sp-train-damaged", "sp-train", "nerfacto", *cpu, "blender-data", "--data",
                                              str(damaged), timeout=180),
        # the host's mipnerf defaults to --vis wandb: a user without a wandb account (no key, no netrc)
        "typed-sp-train-mipnerf-wandb": typed("mipnerf-wandb", "sp-train", "mipnerf", *cpu, *blender, timeout=300, env={
            "WANDB_MODE": "online", "WANDB_API_KEY": "", "HOME": str(root / "typed-mipnerf-wandb")}),
        "eval-other-version": ({"script": "ns-eval", "args": ["--load-config", str(other_version), "--output-path", str(root / "eval-o" / "e.json")]}, root / "eval-o"),
        "mesh-truncated": ({"script": "sp-export-mesh", "args": ["--load-config", str(truncated), "--output-dir", str(root / "mesh-t"), "--resolution", "16"]}, root / "mesh-t"),
        "mesh-missing-class": ({"script": "sp-export-mesh", "args": ["--load-config", str(missing_class), "--output-dir", str(root / "mesh-m")]}, root / "mesh-m"),
        "mesh-missing-config": ({"script": "sp-export-mesh", "args": ["--load-config", str(root / "nowhere.yml"), "--output-dir", str(root / "mesh-n")]}, root / "mesh-n"),
        "train-load-dir-truncated": train("load-dir", blender, "--load-dir", str(ckpt.parent)),
        "train-colmap": train("colmap", ["blender-data", "--data", str(colmap)]),
        "train-ns-capture": train("capture", ["sdfstudio-data", "--data", str(capture)]),
        "train-damaged-image": train("damaged", ["blender-data", "--data", str(damaged)]),
        "train-cuda": train("cuda", blender, "--machine.device-type", "cuda"),
        "train-cpu-two-devices": train("cpu-2", blender, "--machine.device-type", "cpu", "--machine.num-devices", "2"),
        "train-no-device": train("cpu-0", blender, "--machine.device-type", "cpu", "--machine.num-devices", "0"),
        "train-nan": train("nan", blender, "--max-num-iterations", "8", "--steps-per-save", "1000",
                           *[a for g in ("fields", "field-grid", "field-background") for a in (f"--optimizers.{g}.optimizer.lr", "1e30")]),
        "train-full-disk-config": train("full-config", blender, fsize=0),
        "train-full-disk-checkpoint": train("full-ckpt", blender, "--max-num-iterations", "1", "--steps-per-save", "1",
                                            fsize=1_000_000),
    }
    if read_only_ok:
        plan["mesh-read-only"] = ({"script": "sp-export-mesh", "args": ["--load-config", str(intact), "--output-dir", str(read_only / "mesh")]}, read_only)
    before = {name: listing(folder) for name, (_, folder) in plan.items()}
    watched = {p.parent.parent.parent.parent.name: p.parent for p in (truncated, other_version, missing_class, intact)}
    before_runs = {k: listing(v) for k, v in watched.items()}
    # the real console script, started first: its start-up (nerfstudio's imports) overlaps the server's
    real = subprocess.Popen([command("ns-eval"), "--load-config", str(truncated), "--output-path", str(root / "eval-t" / "e.json")],
                            env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    plan["eval-truncated"] = (None, root / "eval-t")
    before["eval-truncated"] = listing(root / "eval-t")
    try:  # the session's fork server (tests/nerfstudio/conftest.py)
        results = ns_server.run([dict(case, name=name) for name, (case, _) in plan.items() if case is not None], parallel=2)
        out, err = real.communicate(timeout=600)
    finally:
        if real.poll() is None:
            real.kill()
        if read_only_ok:
            undo_read_only(read_only)
    results["eval-truncated"] = {"name": "eval-truncated (the real ns-eval)", "rc": real.returncode, "stdout": out, "stderr": err}
    assert {k: listing(v) for k, v in watched.items()} == before_runs, "a command changed a run it loaded"
    return {name: (results[name], before[name], listing(folder)) for name, (_, folder) in plan.items()}


def check(cases, name, *says, prog) -> str:
    result, before, after = cases[name]
    line = one_line_error(result, *says, prog=prog)
    assert after == before, f"[{name}] wrote into {sorted(set(after) ^ set(before)) or 'existing files'}"
    return line


def typed_refusal(cases, name, *says, prog="ns-train") -> str:
    """A command typed as a user types it was refused in one line with nothing written: no ./outputs."""
    line = check(cases, name, *says, prog=prog)
    assert cases[name][2] == {}, f"[{name}] left {sorted(cases[name][2])}"
    return line


@pytest.mark.parametrize("name, prog", [("typed-neus-no-device", "ns-train"), ("typed-sp-train-no-device", "sp-train")])
def test_no_device_flag_on_a_machine_without_cuda_names_the_cpu_flag(cases, name, prog):
    """nerfstudio's default device is cuda: a CPU-only user who types no device flag gets the flag to add."""
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    typed_refusal(cases, name, "CUDA is not available", "--machine.device-type cpu", prog=prog)


def test_nerfstudio_data_default_on_a_blender_scene_names_blender_data(cases):
    """No dataparser named: nerfstudio-data, the default, reads transforms.json (it was a FileNotFoundError
    traceback after config.yml was written)."""
    typed_refusal(cases, "typed-nerfacto-no-dataparser", "transforms.json: file not found", "transforms_train.json",
                  "blender-data --data")


@pytest.mark.parametrize("name, says", [
    ("typed-tensorf-alpha-grid", ("--pipeline.model.sp.alpha-grid True cannot learn on TensoRF",)),
    ("typed-nerfacto-reflect", ("--pipeline.model.sp.boundary reflect needs a bounded scene", "NerfactoModel",
                                "--pipeline.model.sp.boundary none")),
    ("typed-num-samples-sp-off", ("--pipeline.model.sp.num-samples 2 has no effect with SP off",)),
])
def test_sp_settings_that_cannot_act_are_refused_before_the_run_folder_is_written(cases, name, says):
    typed_refusal(cases, name, *says)


def test_sp_train_on_a_host_method_names_a_damaged_image_instead_of_hanging(cases):
    """nerfacto's own data manager caches images in worker processes: a damaged one stopped a worker and
    the run hung behind its traceback."""
    result = cases["typed-sp-train-damaged-image"][0]
    assert result["rc"] != -9, f"killed after {result['seconds']} s: it hung\n{result['stderr'][-3000:]}"
    typed_refusal(cases, "typed-sp-train-damaged-image", "r_2.png: cannot be read as an image", "frame 2 of transforms_train.json",
                  prog="sp-train")


def test_our_methods_default_to_the_viewer_not_wandb():
    """nerfstudio's TrainerConfig defaults to --vis wandb, which stops a user without an account: every
    method of ours (sp-mipnerf, sp-vanilla-nerf and freenerf-lite inherited it) defaults to the viewer."""
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    ours = {name: config.vis for name, config in methods.items() if hasattr(config.pipeline.model, "sp")}
    assert {"sp-mipnerf", "sp-vanilla-nerf", "freenerf-lite", "sp-nerfacto", "sp-neus"} <= set(ours), sorted(ours)
    assert {name: vis for name, vis in ours.items() if vis != "viewer"} == {}


def test_sp_train_on_a_host_method_defaulting_to_wandb_without_an_account_is_one_line(cases):
    """sp-train keeps the host method's own --vis default (mipnerf: wandb); without an account wandb's
    UsageError was a traceback."""
    result = cases["typed-sp-train-mipnerf-wandb"][0]
    one_line_error(result, "--vis wandb: wandb could not start", "wandb login", "--vis viewer", prog="sp-train")


def test_ns_eval_truncated_checkpoint(cases):
    check(cases, "eval-truncated", "step-000000001.ckpt", "cannot be read as a PyTorch checkpoint", "truncated", prog="ns-eval")


def test_ns_eval_config_of_another_version(cases):
    check(cases, "eval-other-version", "--load-config", "other-version", "another version", "pipeline.model.sp.retired_option",
          prog="ns-eval")


def test_sp_export_mesh_truncated_checkpoint(cases):
    check(cases, "mesh-truncated", "step-000000001.ckpt", "not a complete PyTorch checkpoint", prog="sp-export-mesh")


def test_sp_export_mesh_config_naming_a_missing_class(cases):
    check(cases, "mesh-missing-class", "--load-config", "sp_plugins.nerfstudio.retired", "another version", prog="sp-export-mesh")


def test_ns_train_load_dir_with_a_truncated_checkpoint(cases):
    check(cases, "train-load-dir-truncated", "--load-dir", "step-000000001.ckpt", "not a complete PyTorch checkpoint",
          prog="ns-train")


def test_ns_train_colmap_folder_given_to_blender_data(cases):
    check(cases, "train-colmap", "transforms_train.json: file not found", "COLMAP reconstruction", "ns-process-data",
          prog="ns-train")


def test_ns_train_nerfstudio_capture_given_to_sdfstudio_data(cases):
    check(cases, "train-ns-capture", "meta_data.json: file not found", "transforms.json", "nerfstudio-data --data", prog="ns-train")


def test_ns_train_damaged_image(cases):
    check(cases, "train-damaged-image", "r_2.png: cannot be read as an image", "frame 2 of transforms_train.json", prog="ns-train")


def test_ns_train_cuda_on_a_machine_without_it(cases):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    check(cases, "train-cuda", "--machine.device-type cuda", "CUDA is not available", "--machine.device-type cpu", prog="ns-train")


def test_ns_train_two_cpu_devices(cases):
    """nerfstudio's launcher asserts CUDA for more than one device (a traceback after writing the run folder)."""
    check(cases, "train-cpu-two-devices", "--machine.num-devices 2", "--machine.device-type cuda", "--machine.num-devices 1",
          prog="ns-train")


def test_ns_train_no_device_at_all(cases):
    """nerfstudio's launcher stopped with a traceback (``world_size cannot be 0``); the preflight refuses it first."""
    check(cases, "train-no-device", "--machine.num-devices 0", "at least one device", "--machine.num-devices 1", prog="ns-train")


def test_ns_train_loss_turning_nan_stops_naming_the_step(cases):
    result, _, after = cases["train-nan"]
    one_line_error(result, "training step", "the loss became", "--optimizers.fields.optimizer.lr", prog="ns-train")
    assert not [p for p in after if p.endswith(".ckpt")], after  # no NaN checkpoint


def test_ns_train_full_disk_when_writing_its_config(cases):
    check(cases, "train-full-disk-config", "config.yml", "cannot write", "disk is full", prog="ns-train")


def test_ns_train_full_disk_when_writing_a_checkpoint(cases):
    result, _, after = cases["train-full-disk-checkpoint"]
    one_line_error(result, "nerfstudio_models/step-000000000.ckpt", "writing the checkpoint failed", "partial file was removed",
                   prog="ns-train")
    assert not [p for p in after if p.endswith(".ckpt")], after  # no partial checkpoint for a resume to pick up


def test_sp_export_mesh_read_only_output_dir(cases):
    if "mesh-read-only" not in cases:
        pytest.skip("cannot make a read-only folder here (root without chattr +i)")
    check(cases, "mesh-read-only", "--output-dir", "cannot write", "read-only", prog="sp-export-mesh")


def test_sp_export_mesh_missing_load_config(cases):
    check(cases, "mesh-missing-config", "--load-config", "nowhere.yml", "config file not found", prog="sp-export-mesh")
