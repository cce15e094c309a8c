"""Tiny sdfstudio settings and a subprocess runner, shared by the sdfstudio tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Optional

import pytest

BIN = Path(sys.executable).parent

COMMON = [
    "--machine.num-gpus", "0", "--vis", "tensorboard",
    "--experiment-name", "exp", "--timestamp", "run",
    "--trainer.steps-per-eval-batch", "100000", "--trainer.steps-per-eval-image", "100000",
    "--pipeline.datamanager.train-num-rays-per-batch", "24", "--pipeline.datamanager.eval-num-rays-per-batch", "64",
    "--pipeline.model.eval-num-rays-per-chunk", "256",
    "--pipeline.model.sdf-field.hidden-dim", "32", "--pipeline.model.sdf-field.geo-feat-dim", "15",
    "--pipeline.model.sdf-field.hidden-dim-color", "32", "--pipeline.model.sdf-field.num-levels", "4",
    "--pipeline.model.sdf-field.log2-hashmap-size", "11", "--pipeline.model.sdf-field.base-res", "8",
    "--pipeline.model.sdf-field.max-res", "64",
]
NEUS_SAMPLER = [
    "--pipeline.model.num-samples", "8", "--pipeline.model.num-samples-importance", "8",
    "--pipeline.model.num-up-sample-steps", "1", "--pipeline.model.background-model", "none",
]
VOLSDF_SAMPLER = [
    "--pipeline.model.num-samples", "8", "--pipeline.model.num-samples-eval", "16",
    "--pipeline.model.num-samples-extra", "8", "--pipeline.model.background-model", "none",
]
PROPOSALS = ["--pipeline.model.num-proposal-samples-per-ray", "12", "8", "--pipeline.model.num-neus-samples-per-ray", "8"]
TINY = {
    "neus": COMMON + NEUS_SAMPLER + ["--pipeline.model.sdf-field.num-layers", "2"],  # 8 layers need width > input
    "neus-facto": COMMON + PROPOSALS,
    "neuralangelo": COMMON + NEUS_SAMPLER,
    "bakedangelo": COMMON + PROPOSALS + ["--pipeline.model.sdf-field.hash-features-per-level", "2"],
    "volsdf": COMMON + VOLSDF_SAMPLER + ["--pipeline.model.sdf-field.num-layers", "2"],
}
"""Tiny CPU settings per sdfstudio method (few rays, few samples, small tables)."""


def env() -> dict:
    e = dict(os.environ)
    e.update(OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE", MPLBACKEND="Agg", WANDB_MODE="disabled")
    return e


FORKED = ("sp-sdfstudio-train", "sp-sdfstudio-extract-mesh", "ns-train", "ns-eval", "ns-extract-mesh")
"""Console scripts :func:`run` forks from one import of them (tests/helpers/forkserver.py): each start
of an sdfstudio command paid 10-20 s of imports (sdfstudio, its methods, our patches through the
opt-in hook) before a few seconds of work. A real start of each stays in the suite: the README
section's blocks (tests/sdfstudio/test_readme_sdfstudio.py), the hostile-config commands
(test_safe_config_sdf.py), ``ns-train --help`` through the opt-in hook and the kill/resume run."""
_server = None


def fork_server():
    """The session's fork server for :data:`FORKED` (started on first use, stopped by
    tests/sdfstudio/conftest.py at the end of the session)."""
    global _server
    if _server is None:
        from tests.helpers.forkserver import ForkServer

        _server = ForkServer(list(FORKED), env())
    return _server


def close_fork_server() -> None:
    global _server
    if _server is not None:
        _server.close()
        _server = None


def run(args, cwd: Path, timeout: float = 300, expect: int = 0, extra_env: Optional[dict] = None) -> subprocess.CompletedProcess:
    """Run a console script of this venv as a user would, with its command line, folder and
    environment (forked from the session's server when it is one of :data:`FORKED`); fail with its
    output's tail unless it exits ``expect``."""
    cmd = [str(BIN / args[0]), *map(str, args[1:])]
    variables = {**env(), **(extra_env or {})}
    if args[0] in FORKED:
        case = {"name": "run", "script": args[0], "args": cmd[1:], "cwd": str(cwd), "env": variables, "timeout": timeout}
        result = fork_server().run([case])["run"]
        proc = subprocess.CompletedProcess(cmd, result["rc"], result["stdout"], result["stderr"])
    else:
        proc = subprocess.run(cmd, cwd=cwd, env=variables, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != expect:
        tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-40:])
        pytest.fail(f"{' '.join(cmd[:2])} exited {proc.returncode} (expected {expect}):\n{tail}", pytrace=False)
    return proc


def train_args(method: str, base: str, data: Path, out: Path, steps: int, *extra: str) -> list:
    return [
        method, *TINY[base], "--output-dir", out, "--trainer.max-num-iterations", steps,
        "--trainer.steps-per-save", steps, *extra, "sdfstudio-data", "--data", data,
        "--skip-every-for-val-split", "6",
    ]


def run_dir(out: Path, method: str) -> Path:
    """Where sdfstudio writes a run: <output-dir>/<experiment>/<method>/<timestamp>."""
    return out / "exp" / method / "run"


# -- in process: any sdfstudio method's config, shrunk to a few CPU seconds -------------------------------
TINY_FIELD = dict(hidden_dim=32, geo_feat_dim=15, hidden_dim_color=32, num_levels=4, log2_hashmap_size=11, base_res=8,
                  max_res=64, hash_features_per_level=2)
"""sdf_field sizes (as the command-line settings of :data:`COMMON`)."""
TINY_SAMPLERS = dict(num_samples=8, num_samples_importance=8, num_up_sample_steps=1, num_samples_outside=4,
                     num_samples_eval=16, num_samples_extra=8, num_samples_interval=8, num_marching_steps=16,
                     num_neus_samples_per_ray=8, eval_num_rays_per_chunk=256)
"""Sampler sizes, set where the model config has them."""
TINY_PROPOSAL_NET = dict(hidden_dim=16, log2_hashmap_size=11, num_levels=4, max_res=64)


def pairs_file(data: Path, n_train: int) -> Path:
    """``pairs.txt`` for GeoNeuS patch warping (``--load-pairs True``): each training image, then
    the others as its sources (sdfstudio reads the numbers of the names)."""
    lines = [" ".join(f"{j:03d}.png" for j in [i] + [k for k in range(n_train) if k != i]) for i in range(n_train)]
    path = data / "pairs.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


def tiny_config(config, data: Path, out: Path, steps: int = 2):
    """A deep copy of sdfstudio trainer config ``config`` that trains ``steps`` CPU steps on the
    SDFStudio-layout scene ``data`` (every 6th frame held out) and writes under ``out``."""
    import copy
    import dataclasses

    from nerfstudio.data.datamanagers.base_datamanager import FlexibleDataManagerConfig
    from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig

    config = copy.deepcopy(config)
    config.machine.num_gpus = 0
    config.vis = "tensorboard"
    config.viewer.quit_on_train_completion = True
    config.output_dir, config.experiment_name, config.timestamp = Path(out), "exp", "run"
    trainer = config.trainer
    trainer.max_num_iterations = trainer.steps_per_save = steps
    trainer.steps_per_eval_batch = trainer.steps_per_eval_image = trainer.steps_per_eval_all_images = 100_000
    datamanager = config.pipeline.datamanager
    patch_warping = isinstance(datamanager, FlexibleDataManagerConfig)  # GeoNeuS: needs source views
    datamanager.dataparser = SDFStudioDataParserConfig(data=Path(data), skip_every_for_val_split=6, load_pairs=patch_warping)
    datamanager.train_num_rays_per_batch, datamanager.eval_num_rays_per_batch = 24, 64
    model = config.pipeline.model
    for name, value in TINY_SAMPLERS.items():
        if hasattr(model, name):
            setattr(model, name, value)
    if hasattr(model, "background_model"):
        model.background_model = "none"
    if hasattr(model, "num_proposal_samples_per_ray"):
        model.num_proposal_samples_per_ray = tuple([12, 8][: len(model.num_proposal_samples_per_ray)])
    if hasattr(model, "proposal_net_args_list"):
        model.proposal_net_args_list = [{**args, **TINY_PROPOSAL_NET} for args in model.proposal_net_args_list]
    sizes = {name: value for name, value in TINY_FIELD.items() if hasattr(model.sdf_field, name)}
    sizes.update(num_layers=min(model.sdf_field.num_layers, 2), num_layers_color=min(model.sdf_field.num_layers_color, 2))
    if getattr(model.sdf_field, "fd_step", None) is not None:  # SP's fixed step, at the shrunk resolution
        sizes["fd_step"] = model.sdf_field.fd_step * model.sdf_field.max_res / TINY_FIELD["max_res"]
    model.sdf_field = dataclasses.replace(model.sdf_field, **sizes)
    return config


def train_in_process(config):
    """sdfstudio's own Trainer on the CPU (as ``train_loop`` runs it); returns the trainer."""
    from nerfstudio.engine.trainer import Trainer

    from sp_plugins.patches.sdfstudio_cuda import cpu_meaning

    with cpu_meaning():
        trainer = Trainer(config, local_rank=0, world_size=0)
        trainer.setup()
        trainer.train()
    return trainer
