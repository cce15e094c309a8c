"""The task trainers' base: :class:`ResumableTrainer` (checkpoint state, per-step numbers read from
the device in batches, the set-up every task shares), :class:`SDFTrainer` (the plain field's mesh
and metrics for the two SDF tasks) and :func:`run_to_end`."""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from typing import Any, Mapping, Optional, Sequence

import torch
from tqdm.auto import tqdm

from sp_plugins.core.run import SPRun
from sp_plugins.geometry import evaluate_grid, largest_component, mesh_from_grid, mesh_metrics
from sp_plugins.tasks.common import StepTimer, counting_bar, stage
from sp_plugins.tasks.fields import NeuralField


LOG_EVERY = 25
"""Steps between two reads of a fit's per-step numbers from the device (and its non-finite check)."""


def run_to_end(trainer, desc: str, callback=None, progress: bool = False) -> None:
    """Step ``trainer`` (anything with ``step()``, ``done``, ``step_index`` and ``config.steps``)
    to its last step, with a tqdm bar showing the loss and alpha every :data:`LOG_EVERY` steps;
    ``callback(trainer, record)`` after each step. The numbers are read from the device only then
    (and at the end), never per step."""
    bar = tqdm(total=trainer.config.steps, initial=trainer.step_index, disable=not progress, desc=desc)
    while not trainer.done:
        record = trainer.step()
        bar.update(1)
        if progress and (trainer.step_index % LOG_EVERY == 0 or trainer.done):
            bar.set_postfix(loss=f"{record['loss']:.4g}", alpha=f"{record['alpha']:.3g}")
        if callback is not None:
            callback(trainer, record)
    flush = getattr(trainer, "flush", None)
    if flush is not None:
        flush()  # the last steps' numbers, and their non-finite check
    bar.close()


class StepRecord(Mapping):
    """One step's numbers (``record["loss"]``), read from the device when first looked at: a loop
    that never looks costs no host-device sync."""

    def __init__(self, trainer: "ResumableTrainer", position: int, keys: Sequence[str]) -> None:
        self._trainer, self._position, self._keys = trainer, position, tuple(keys)

    def __getitem__(self, key: str) -> float:
        if key not in self._keys:
            raise KeyError(key)
        return self._trainer.history[key][self._position]

    def __iter__(self):
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __repr__(self) -> str:
        return f"StepRecord({dict(self)})"


class ResumableTrainer:
    """``state_dict`` / ``load_state_dict`` for the task trainers: everything a fit's trajectory
    depends on that is not rebuilt from its config and data (those are rebuilt identically on
    resume: the network's initialisation, the sample pool, the frame). A trainer has ``field``,
    ``sp``, ``optimizer``, ``generator`` (the batches), ``step_index``, ``history``, ``timer`` and
    optionally ``scheduler``; :meth:`_extra_state` / :meth:`_load_extra_state` add its own.

    It also keeps the per-step numbers: a step hands them to :meth:`_finish_step` as device
    tensors, and they are read in one go (one host-device sync) every :data:`LOG_EVERY` steps or
    when ``history`` / a record is read, checking the loss for NaN / inf then: a step on a GPU
    never waits for its own numbers."""

    _pending: list
    _history: dict
    # set by each task's __init__
    config: Any  # the task's own config dataclass
    device: torch.device
    field: NeuralField
    sp: SPRun
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler  # only where the task has one (checked with getattr)

    @property
    def history(self) -> dict:
        """``{name: [value per step]}`` as Python floats (reads the steps not read yet)."""
        self.flush()
        return self._history

    @history.setter
    def history(self, value: Mapping) -> None:
        self._history = defaultdict(list, {k: list(v) for k, v in value.items()})
        self._pending = []

    def _finish_step(self, values: Mapping[str, Any]) -> StepRecord:
        """Count the step and keep its numbers (tensors stay on the device, detached)."""
        position = len(self._history.get("loss", ())) + len(self._pending)
        kept = {k: v.detach() if isinstance(v, torch.Tensor) else float(v) for k, v in values.items()}
        self._pending.append((self.step_index, kept))
        self.step_index += 1
        if self.step_index % LOG_EVERY == 0:
            self.flush()
        return StepRecord(self, position, tuple(kept))

    def flush(self) -> None:
        """Read the pending steps' numbers from the device (one sync) into ``history``; a loss that
        is not finite stops the fit, naming the first step where it happened."""
        if not self.__dict__.get("_pending"):
            return
        pending, self._pending = self._pending, []
        tensors = [v.reshape(()).to(torch.float64) for _, values in pending for v in values.values() if isinstance(v, torch.Tensor)]
        read = iter(torch.stack(tensors).tolist() if tensors else [])
        rows = [(step, {k: next(read) if isinstance(v, torch.Tensor) else v for k, v in values.items()}) for step, values in pending]
        for step, values in rows:
            if not math.isfinite(values["loss"]):
                raise FloatingPointError(self._diverged(step, values["loss"]))
            for k, v in values.items():
                self._history[k].append(v)
        self.timer.times  # noqa: B018  (the steps' events completed before the numbers: free now)

    def _diverged(self, step: int, loss: float) -> str:
        """The one-line stop for a loss that became NaN / inf at ``step``."""
        return f"step {step}: the loss became {loss}; the fit diverged: lower --lr (now {self.config.lr:g}, e.g. 10x smaller)"

    def state_dict(self) -> dict:
        state = {
            "step": self.step_index,
            "field": self.field.state_dict(),
            # schedule position, alpha grid, noise generator state (the preconditioner's, as checkpoints always held)
            "sp": self.sp.state_dict()["preconditioner"],
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "history": {k: list(v) for k, v in self.history.items()},
            "step_times": list(self.timer.times),
        }
        if getattr(self, "scheduler", None) is not None:
            state["scheduler"] = self.scheduler.state_dict()
        state.update(self._extra_state())
        return state

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        self.sp.load_state_dict({"preconditioner": state["sp"]})
        self.optimizer.load_state_dict(state["optimizer"])
        if getattr(self, "scheduler", None) is not None:
            self.scheduler.load_state_dict(state["scheduler"])
        self.generator.set_state(state["generator"])
        self.step_index = int(state["step"])
        self.history = state["history"]
        self.timer.times = list(state.get("step_times", []))
        self._load_extra_state(state)

    def _extra_state(self) -> dict:
        return {}

    def _load_extra_state(self, state: dict) -> None:
        pass

    @property
    def done(self) -> bool:
        return self.step_index >= self.config.steps

    # -- set-up shared by the tasks (each trainer's __init__ calls these in this order) -------------
    def _build_field(self, **kwargs):
        """``NeuralField(config.encoding, **kwargs)`` on the device, initialised from ``config.seed``
        alone: torch's global generator is forked, so neither what ran before nor the fit's own
        draws change the initialisation, and it leaves the caller's stream as it was."""
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.config.seed)
            return NeuralField(self.config.encoding, **kwargs).to(self.device)

    def _setup_sp(self, bounds: tuple[float, float], dim: int):
        """``self.sp``, an :class:`~sp_plugins.SPRun` over ``config.steps`` from ``config.sp`` on the trainer's
        device (a task's step is a plain loop: ``sp.step_pre``, ``sp.blurred``, ``sp.step_post``); returns the
        config it was built from. Unless ``sp.seed`` is set, the noise is seeded with ``seed + 1``: a stream
        of its own, not the batches' (``seed``), and the same for every run of one seed. The task's optimizer
        steps an alpha grid (:meth:`_param_groups`), so a checkpoint keeps one optimizer."""
        config = self.config
        sp_config = config.sp if config.sp.seed is not None else dataclasses.replace(config.sp, seed=config.seed + 1)
        self.sp = SPRun(sp_config, total_steps=config.steps, bounds=bounds, dim=dim, alpha_grid_optimizer=False).to(self.device)
        return sp_config

    def _param_groups(self, sp_config) -> list[dict]:
        """The optimizer groups: the field at ``config.lr``, and SP's learnable alpha grid (when
        ``sp.alpha_grid`` built one) at ``sp.alpha_grid_lr``."""
        groups = [{"params": list(self.field.parameters()), "lr": self.config.lr}]
        if self.sp.alpha_grid is not None:
            groups.append({"params": list(self.sp.alpha_grid.parameters()), "lr": sp_config.alpha_grid_lr})
        return groups

    def _start_steps(self) -> None:
        """Step 0: the batch generator seeded with ``config.seed``, empty history, a step timer."""
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(self.config.seed)
        self.step_index = 0
        self.history = defaultdict(list)
        self.timer = StepTimer(self.device)


class SDFTrainer(ResumableTrainer):
    """What the two SDF tasks (point cloud, direct SDF) share once trained: the plain field in the
    ``[-1, 1]^3`` frame, its mesh, and a mesh's metrics against the ground truth, raw and of its
    largest component. A trainer has ``field`` (``[n, 3] -> [n, 1]``) and ``config.mesh_resolution``,
    ``refine``, ``metric_points``, ``fscore_threshold`` and ``seed``."""

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """The plain (unperturbed) field in the frame."""
        self.field.eval()
        return self.field(x).squeeze(-1)

    def mesh(self, resolution: Optional[int] = None, refine: Optional[int] = None, progress: bool = False):
        """Zero level set in the frame, and field diagnostics: ``negative_fraction`` of the grid
        (a sound SDF of an object is mostly positive), the resolution and refinement. ``progress``
        shows what it is doing (it takes a while at high resolutions)."""
        res = resolution or self.config.mesh_resolution
        ref = self.config.refine if refine is None else refine
        with stage(f"meshing: the field on a {res}^3 grid", progress):
            sdf, bar = counting_bar(self.sdf, res**3, "grid points", progress)
            with torch.no_grad():
                volume = evaluate_grid(sdf, (-1.0, 1.0), res, device=self.device)
            bar.close()
        with stage(f"meshing: marching cubes, {ref} bisection steps per vertex", progress):
            mesh = mesh_from_grid(volume, (-1.0, 1.0), self.sdf, refine=ref, device=self.device)
        info = {"negative_fraction": float((volume < 0).mean()), "resolution": res, "refine": ref}
        return mesh, info

    def mesh_metrics(self, mesh, gt, metric_points: Optional[int] = None, progress: bool = False) -> dict:
        """Chamfer, normal consistency and F-score of ``mesh`` against ``gt`` (both in the frame),
        and the same after keeping the largest component of ``mesh`` (``clean_*``)."""
        c = self.config
        n = metric_points or c.metric_points
        with stage(f"measuring: Chamfer, normal consistency and F-score on {n} points per mesh", progress):
            m = mesh_metrics(mesh, gt, n_points=n, fscore_threshold=c.fscore_threshold, seed=c.seed)
        with stage("measuring: the same for the largest component", progress):
            mc = mesh_metrics(largest_component(mesh), gt, n_points=n, fscore_threshold=c.fscore_threshold, seed=c.seed)
        return dict(m, **{f"clean_{k}": v for k, v in mc.items() if k not in ("unit", "n_points", "fscore_threshold")})
