"""Train the same command twice, each in a fresh process and folder, and compare the checkpoints
tensor by tensor (bitwise): what "a run repeats" means in tests/*/test_repeatable_runs.py."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch

Command = Callable[[Path], Sequence[str]]


def env(threads: int) -> dict:
    """The user's environment with ``threads`` torch threads; idle OpenMP threads sleep, so two runs
    side by side on two cores do not spin against each other."""
    return dict(os.environ, OMP_NUM_THREADS=str(threads), OMP_WAIT_POLICY="PASSIVE", MPLBACKEND="Agg",
                WANDB_MODE="disabled")


def run_side_by_side(commands: Sequence[Sequence[str]], threads: int, cwd: Path, timeout: int = 600,
                     extra_env: Optional[Sequence[dict]] = None) -> List[str]:
    """Start every command at once (each its own process, ``extra_env[i]`` added to its environment), wait for
    all; fail with the tail of any that failed. Returns each one's output (stdout and stderr)."""
    extra = list(extra_env or [{}] * len(commands))
    procs = [subprocess.Popen(list(map(str, c)), env={**env(threads), **e}, cwd=cwd, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for c, e in zip(commands, extra)]
    outputs = [p.communicate(timeout=timeout)[0] for p in procs]
    for command, proc, output in zip(commands, procs, outputs):
        assert proc.returncode == 0, f"{' '.join(map(str, command))} exited {proc.returncode}:\n{output[-3000:]}"
    return outputs


def train_twice(command: Command, root: Path, threads: int = 1, timeout: int = 600) -> Tuple[Path, Path]:
    """``command(out)`` for two fresh output folders, side by side; returns the two folders."""
    outs = (root / "run-a", root / "run-b")
    run_side_by_side([command(out) for out in outs], threads, root, timeout)
    return outs


def tensors(obj, prefix: str = "") -> Dict[str, torch.Tensor]:
    """Every tensor in a checkpoint's nested dicts and lists, by its path."""
    found: Dict[str, torch.Tensor] = {}
    if isinstance(obj, dict):
        for key, value in obj.items():
            found.update(tensors(value, f"{prefix}/{key}"))
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            found.update(tensors(value, f"{prefix}/{i}"))
    elif torch.is_tensor(obj):
        found[prefix] = obj
    return found


def checkpoint(folder: Path, pattern: str) -> Dict[str, torch.Tensor]:
    """The tensors of the one checkpoint matching ``pattern`` under ``folder``."""
    found = sorted(folder.glob(pattern))
    assert len(found) == 1, f"{folder}: {len(found)} files match {pattern}"
    return tensors(torch.load(found[0], map_location="cpu", weights_only=False))


def differing(a: Dict[str, torch.Tensor], b: Dict[str, torch.Tensor]) -> List[str]:
    """Paths whose tensors are not bitwise equal (or exist on one side only)."""
    out = sorted(set(a) ^ set(b))
    for key in sorted(set(a) & set(b)):
        x, y = a[key], b[key]
        if x.shape != y.shape or x.dtype != y.dtype or not torch.equal(x, y):
            out.append(f"{key} (max |diff| {(x.double() - y.double()).abs().max().item():.3g})"
                       if x.shape == y.shape and x.is_floating_point() else key)
    return out


def floating(a: Dict[str, torch.Tensor]) -> int:
    return sum(t.is_floating_point() for t in a.values())
