"""Tiny sdfstudio settings and a subprocess runner, shared by the sdfstudio tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

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
PROPOSALS = ["--pipeline.model.num-proposal-samples-per-ray", "12", "8", "--pipeline.model.num-neus-samples-per-ray", "8"]
TINY = {
    "neus": COMMON + NEUS_SAMPLER + ["--pipeline.model.sdf-field.num-layers", "2"],  # 8 layers need width > input
    "neus-facto": COMMON + PROPOSALS,
    "neuralangelo": COMMON + NEUS_SAMPLER,
    "bakedangelo": COMMON + PROPOSALS + ["--pipeline.model.sdf-field.hash-features-per-level", "2"],
}
"""Tiny CPU settings per sdfstudio method (few rays, few samples, small tables)."""


def env() -> dict:
    e = dict(os.environ)
    e.update(OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE", MPLBACKEND="Agg", WANDB_MODE="disabled")
    return e


def run(args, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run a console script of this venv as a user would; fail with its output's tail."""
    cmd = [str(BIN / args[0]), *map(str, args[1:])]
    proc = subprocess.run(cmd, cwd=cwd, env=env(), capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-40:])
        pytest.fail(f"{' '.join(cmd[:2])} exited {proc.returncode}:\n{tail}", pytrace=False)
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
