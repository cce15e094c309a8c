"""SP's settings: what the preconditioner reads, validated once (:class:`SPSettings`).

:class:`~sp_plugins.core.config.SPConfig` adds nerfstudio's ``_target`` (the preconditioner it
builds); the preconditioner reads only these settings, so the two modules import each other in one
direction only (config -> preconditioner -> settings)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Optional

from sp_plugins.core.alpha_grid import AlphaGridParameterization, check_parameterization
from sp_plugins.core.boundary import BoundaryKind, check_boundary_kind
from sp_plugins.core.noise import NoiseKind, check_noise_kind
from sp_plugins.core.schedule import SCHEDULE_KINDS, ScheduleKind

AlphaGridMode = Literal["replace", "scaled"]
ALPHA_GRID_MODES: tuple[str, ...] = ("replace", "scaled")


@dataclass
class SPSettings:
    """Stochastic preconditioning settings (the fields of :class:`~sp_plugins.core.config.SPConfig`)."""

    enabled: bool = True
    """Perturb query positions while training. False gives the plain baseline."""
    alpha0: float = 0.01
    """Initial alpha: the standard deviation of the offset per axis, in scene units (or a
    fraction of the scene bounding-box diagonal with relative_to_diagonal)."""
    relative_to_diagonal: bool = False
    """Read alpha0 as a fraction of the scene bounding-box diagonal (the paper: 1-2%)."""
    schedule: ScheduleKind = "exponential"
    """constant | step (alpha0, then 0) | exponential (decays to exactly 0) | linear."""
    end: float = 0.2
    """When alpha reaches 0: a fraction of training in (0, 1], or an absolute step > 1; at the
    last step at the latest (end 1.0 keeps SP on for every step but the last)."""
    final_ratio: float = 1e-3
    """Exponential schedule only: decades of decay before the shift to 0 (1e-3 = three)."""
    noise: NoiseKind = "gaussian"
    """gaussian | uniform | squared-gaussian, all with unit variance per axis."""
    boundary: BoundaryKind = "reflect"
    """reflect (bounded scenes) | clamp (comparison only) | none (unbounded or contracted)."""
    num_samples: int = 1
    """Average the field over K perturbations (the paper's multi-sample variant; K x cost)."""
    alpha_grid: bool = False
    """Learn a spatially varying alpha(x) on a grid in place of the annealed scalar (the paper's
    variant): the grid alone gives alpha during the SP phase (until ``end``; all of training with
    schedule constant), then SP is off. alpha0 only serves as the grid's default initial value."""
    alpha_grid_mode: AlphaGridMode = "replace"
    """replace (the paper: the grid alone, then off) | scaled (the grid times the schedule's decay
    from 1 to 0, whatever alpha0 is)."""
    alpha_grid_resolution: int = 32
    """Cells per axis of the alpha grid (the paper: 128 on a GPU)."""
    alpha_grid_init: Optional[float] = None
    """Initial alpha of the grid; None uses alpha0 (one of them must be > 0)."""
    alpha_grid_lr: float = 1e-3
    """Adam learning rate of the alpha grid (in the units of its parameterisation)."""
    alpha_grid_parameterization: AlphaGridParameterization = "log"
    """What the optimizer moves: log (log-alpha: lr is a relative step) | alpha (alpha itself, the
    paper's words: lr in scene units) | softplus (sp-plugins 0.1.0). See AlphaGrid."""
    seed: Optional[int] = None
    """Seed of the perturbation noise (each distributed rank uses seed + rank). None draws the
    seed from torch's global generator at the first perturbation. Either way the noise
    generator's state is in the checkpoint, so a resumed run draws the noise an uninterrupted
    run would have drawn."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise a ValueError naming the first bad setting."""
        check_noise_kind(self.noise)
        check_boundary_kind(self.boundary)
        if self.schedule not in SCHEDULE_KINDS:
            raise ValueError(f"schedule={self.schedule!r} is not a schedule; allowed values: {', '.join(SCHEDULE_KINDS)}")
        if not (math.isfinite(self.alpha0) and self.alpha0 >= 0):
            raise ValueError(f"alpha0={self.alpha0!r}: must be a finite number >= 0")
        if not (math.isfinite(self.end) and self.end > 0):
            raise ValueError(f"end={self.end!r}: give a fraction of training in (0, 1] or an absolute end step > 1")
        if not 0.0 < self.final_ratio < 1.0:  # NaN too; checked here, not first when the schedule is built mid-setup
            raise ValueError(f"final_ratio={self.final_ratio!r}: must lie in (0, 1)")
        if self.num_samples < 1:
            raise ValueError(f"num_samples={self.num_samples}: must be >= 1")
        if self.alpha_grid_init is not None and not (math.isfinite(self.alpha_grid_init) and self.alpha_grid_init > 0):
            raise ValueError(f"alpha_grid_init={self.alpha_grid_init!r}: must be a finite number > 0")
        if self.alpha_grid_mode not in ALPHA_GRID_MODES:
            raise ValueError(f"alpha_grid_mode={self.alpha_grid_mode!r}: allowed values: {', '.join(ALPHA_GRID_MODES)}")
        check_parameterization(self.alpha_grid_parameterization)
        if not (math.isfinite(self.alpha_grid_lr) and self.alpha_grid_lr >= 0):  # 0 freezes the grid
            raise ValueError(f"alpha_grid_lr={self.alpha_grid_lr!r}: must be a finite number >= 0")
        if self.alpha_grid_resolution < 2:
            raise ValueError(f"alpha_grid_resolution={self.alpha_grid_resolution}: must be >= 2")
