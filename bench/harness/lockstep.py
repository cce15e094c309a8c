"""The lockstep pair driver: trainers of one host trained side by side in one process.

Every run of a group starts from the same weights (the RNG seeded before its trainer is built) and
sees the same rays and jitter at every step (torch, numpy and Python's ``random`` re-seeded per
step); the runs' iterations alternate (A B C, C B A, ...), so their per-step times are measured
under the same machine load. Host neutral: both nerfstudio 1.x and sdfstudio have
``nerfstudio.engine.callbacks``; how a trainer is built is the host module's
(:mod:`bench.harness.nerfstudio`, :mod:`bench.harness.sdfstudio`).
"""

from __future__ import annotations

import logging
import statistics
import time
from typing import Callable, Dict, List

from bench.harness.common import seed_everything


class Run:
    """One trainer driven step by step (the loop of ``Trainer.train`` without viewer, writers,
    evaluations and checkpoints)."""

    def __init__(self, name: str, make_trainer: Callable[[], object], seed: int) -> None:
        from nerfstudio.engine.callbacks import TrainingCallbackLocation

        self.name = name
        self.where = TrainingCallbackLocation
        seed_everything(seed)  # the cached image order comes from Python's random (the hosts' CacheDataloader)
        self.trainer = make_trainer()
        self.losses: List[float] = []
        self.times: List[float] = []
        self.alphas: List[float] = []

    @property
    def model(self):
        return self.trainer.pipeline.model

    def step(self, step: int, seed: int) -> None:
        trainer = self.trainer
        trainer.pipeline.train()
        for cb in trainer.callbacks:
            cb.run_callback_at_location(step, self.where.BEFORE_TRAIN_ITERATION)
        seed_everything(seed * 1_000_003 + step)  # the same rays and jitter for every run
        t0 = time.perf_counter()
        loss, _, _ = trainer.train_iteration(step)
        self.times.append(time.perf_counter() - t0)
        for cb in trainer.callbacks:
            cb.run_callback_at_location(step, self.where.AFTER_TRAIN_ITERATION)
        self.losses.append(float(loss.detach()))
        sp = getattr(self.model, "sp", None)
        self.alphas.append(float(getattr(sp, "alpha", 0.0)))


def train_together(runs: Dict[str, Run], steps: int, seed: int, label: str, log_every: int = 100) -> float:
    """``steps`` steps of every run, alternating; returns the wall time in seconds."""
    t0 = time.time()
    names = list(runs)
    for step in range(steps):
        for name in names if step % 2 == 0 else names[::-1]:
            runs[name].step(step, seed)
        if step % log_every == 0 or step == steps - 1:
            logging.info("%s step %d/%d: %s (%.0f s)", label, step, steps,
                         ", ".join(f"{n} {r.losses[-1]:.4f}" for n, r in runs.items()), time.time() - t0)
    return time.time() - t0


def step_stats(run: Run) -> dict:
    """Median seconds per step (the first tenth, at most 10 steps, skipped), the final loss (mean of
    the last 20) and the loss curve."""
    skip = min(10, len(run.times) // 10)
    return {"median_step_s": statistics.median(run.times[skip:]), "final_loss": statistics.mean(run.losses[-20:]),
            "losses": run.losses}


def run_summary(run: Run, metrics: dict) -> dict:
    """``metrics`` with :func:`step_stats`, the total training time and the alpha curve (200 points at most)."""
    stats = step_stats(run)
    return {
        **metrics,
        "median_step_s": stats["median_step_s"],
        "total_train_s": sum(run.times),
        "final_loss": stats["final_loss"],
        "losses": run.losses,
        "alphas": run.alphas[:: max(1, len(run.alphas) // 200)],
    }


def time_ratio(sp: Run, base: Run) -> float:
    """Median over alternating step pairs of SP's time over the baseline's (the first tenth, at most 10 pairs, left out)."""
    skip = min(10, len(sp.times) // 10)
    return statistics.median(s / b for s, b in zip(sp.times[skip:], base.times[skip:]))


def active_time_ratios(sp: Run, base: Run) -> dict:
    """SP's time ratio while its alpha is above 0 (median of pairs, the first 10 left out) and over the whole run."""
    active = [s / b for s, b, a in zip(sp.times, base.times, sp.alphas) if a > 0][10:]
    return {"time_ratio_while_active": statistics.median(active) if active else None,
            "time_ratio_whole_run": sum(sp.times) / sum(base.times)}
