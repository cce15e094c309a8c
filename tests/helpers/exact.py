"""Shared by the exact-value tests of the ``sp-fit`` tasks: a field wrapper that records
what the trainer queried, and the paper's perturbed query from raw seeded draws."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from tests.core.test_properties import fold_reference


class Recorder(nn.Module):
    """``inner``, recording every input it is queried at and every output it gives (the trainer's
    optimizer keeps ``inner``'s parameters: the wrapper has none of its own)."""

    def __init__(self, inner: nn.Module) -> None:
        super().__init__()
        self.inner = inner
        self.inputs: list = []
        self.outputs: list = []

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.inner(x)
        self.inputs.append(x.detach().clone())
        self.outputs.append(out.detach().clone())
        return out


def gaussian_draws(shape, seed: int) -> torch.Tensor:
    """The Gaussian draw of a preconditioner seeded ``seed`` (rank 0), in float64."""
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed)).double()


def folded_query(x: torch.Tensor, alpha, eps: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """``x + alpha * eps`` folded into ``[lo, hi]`` where ``x`` lies inside it (float64, differentiable)."""
    x = x.double()
    lo_t, hi_t = torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64)
    raw = x + alpha * eps
    inside = (x >= lo) & (x <= hi)
    return torch.where(inside, fold_reference(raw, lo_t, hi_t), raw)


def sp_draws(x: torch.Tensor, k: int, seed: int) -> torch.Tensor:
    """The ``k`` Gaussian draws a preconditioner seeded ``seed`` adds to the points ``x`` ``[n, d]``: ``[k, n, d]``,
    or ``[n, d]`` for k = 1 (float64)."""
    return gaussian_draws(((k,) if k > 1 else ()) + tuple(x.shape), seed)


def assert_read_folded(trainer, x: torch.Tensor, alpha, eps: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """A task trainer's step (its field a :class:`Recorder`) read ``x + alpha * eps`` folded into ``[lo, hi]``, some
    queries folded indeed (else the fold went untested). Returns that query (float64, differentiable in ``x`` and
    ``alpha``; ``[k, n, d]`` or ``[n, d]`` as ``eps``)."""
    q = folded_query(x, alpha, eps, lo, hi)
    plain_alpha = alpha.detach() if isinstance(alpha, torch.Tensor) else alpha
    assert ((q - (x.double() + plain_alpha * eps)).abs() > 1e-3).any()  # some queries were folded
    (read,) = trainer.field.inputs
    torch.testing.assert_close(read.double(), q.detach(), rtol=0, atol=2e-5)
    return q


def fold_sign(x: torch.Tensor, alpha, eps: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """d(folded query)/dx per coordinate: -1 where the mirror flipped it an odd number of times."""
    u = torch.remainder((x.double() + alpha * eps - lo) / (hi - lo), 2.0)
    inside = (x >= lo) & (x <= hi)
    return torch.where(inside & (u > 1.0), -1.0, 1.0).double()


def assert_alpha_grid_frozen_once_sp_ends(trainer) -> None:
    """Four steps of a task trainer whose SP (alpha grid on) ends after two: the grid learns while SP is
    on, then no step moves it (SP no longer reads it, so it has no gradient and the optimizer must skip
    it: ``zero_grad(set_to_none=True)``; zeroed gradients would let Adam's momentum drift it)."""
    grids = []
    for _ in range(4):
        trainer.step()
        grids.append([p.detach().clone() for p in trainer.sp.alpha_grid.parameters()])
    assert trainer.history["alpha"] == [0.05, 0.05, 0.0, 0.0]
    assert any(not torch.equal(a, b) for a, b in zip(grids[0], grids[1]))  # it learns while SP is on
    for later in grids[2:]:
        assert all(torch.equal(a, b) for a, b in zip(grids[1], later))


def check_runs_every_iteration_where_named(make, where: str) -> None:
    """``make(record)``: a host training callback (nerfstudio's ``TrainingCallback``, either host) asked
    to call ``record(step)`` ``where`` ("before" or "after") every iteration; it must run at every step,
    at that place and never at the other."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation as At

    calls: list = []

    def record(step: int) -> None:
        calls.append(step)

    callback = make(record)
    here, there = (At.BEFORE_TRAIN_ITERATION, At.AFTER_TRAIN_ITERATION)[:: 1 if where == "before" else -1]
    for step in range(5):
        callback.run_callback_at_location(step, there)
        assert calls == list(range(step)), f"asked for {where} the iteration, it ran at the other place"
        callback.run_callback_at_location(step, here)
    assert calls == [0, 1, 2, 3, 4]


def assert_keyword_only_options(trainer_class: type, config, data, gt_mesh) -> None:
    """A meshed task's trainer takes ``device`` and ``evaluate``'s options by keyword only: a positional third
    argument is refused, not read as the device or the grid resolution."""
    with pytest.raises(TypeError):
        trainer_class(config, data, "cpu")
    trainer = config.setup(data, device="cpu")
    with pytest.raises(TypeError):
        trainer.evaluate(gt_mesh, 8)
