"""The kill/resume driver shared by the nerfstudio and sdfstudio kill-and-resume tests: the global
RNGs of the test session kept apart from a trainer's, the wait for a child's "checkpoint at K is on
disk" file, and bit-for-bit comparison of checkpoints and parameters."""

from __future__ import annotations

import random
import subprocess
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch


@contextmanager
def own_global_rng():
    """ns-train / train_loop re-seed the global RNGs; give the rest of the test session its own back."""
    states = torch.get_rng_state(), np.random.get_state(), random.getstate()
    try:
        yield
    finally:
        torch.set_rng_state(states[0])
        np.random.set_state(states[1])
        random.setstate(states[2])


def restore_global_rng(rng: dict) -> None:
    """Set the global RNGs to ``{"torch", "numpy", "python"}`` states (saved by the killed child at K)."""
    torch.set_rng_state(rng["torch"])
    np.random.set_state(rng["numpy"])
    random.setstate(rng["python"])


def wait_for_ready(proc: subprocess.Popen, ready: Path, what: str, timeout: float = 240) -> str:
    """Wait until the child writes ``ready`` (its pid once its checkpoint is on disk, ``ended`` when it
    stopped without one); fail with the helper's stderr when ``proc`` dies or ``timeout`` passes.
    Returns the file's text."""
    deadline = time.monotonic() + timeout
    while not ready.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            if proc.poll() is None:
                proc.kill()
            err = proc.communicate()[1] or ""
            pytest.fail(f"{what}: no checkpoint to kill at: {err[-3000:]}", pytrace=False)
        time.sleep(0.05)
    text = ready.read_text()
    if text == "ended":
        proc.kill()
        err = proc.communicate()[1] or ""
        pytest.fail(f"{what} ended before its checkpoint to kill at: {err[-3000:]}", pytrace=False)
    return text


def assert_same(a, b, where="") -> None:
    """Nested dicts / lists of tensors and plain values, equal to the bit."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert set(a) == set(b), (where, set(a) ^ set(b))
        for k in a:
            assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (u, v) in enumerate(zip(a, b)):
            assert_same(u, v, f"{where}[{i}]")
    else:
        assert a == b, (where, a, b)


def model_params(trainer) -> dict:
    """A detached copy of the trainer's model parameters, by name."""
    return {k: v.detach().clone() for k, v in trainer.pipeline.model.named_parameters()}


def assert_same_run(trainer, record: dict, full, full_record: dict, steps) -> None:
    """``trainer`` equal to the bit to ``full`` (the uninterrupted run): ``record`` at each of ``steps``, the
    model's parameters, the optimizers' states and the preconditioner's."""
    for step in steps:
        assert_same(record[step], full_record[step], f"step {step}")
    assert_same(model_params(trainer), model_params(full), "parameters")
    assert_same({k: v.state_dict() for k, v in trainer.optimizers.optimizers.items()},
                {k: v.state_dict() for k, v in full.optimizers.optimizers.items()}, "optimizers")
    assert_same(trainer.pipeline.model.sp.state_dict(), full.pipeline.model.sp.state_dict(), "sp")
