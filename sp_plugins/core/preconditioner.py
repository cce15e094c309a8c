"""The module a host holds: SP config + schedule + optional alpha grid, driven by the step."""

from __future__ import annotations

import logging
from typing import Callable, Optional, TypeVar

import torch
from jaxtyping import Float
from torch import Tensor, nn

from sp_plugins.core.alpha_grid import AlphaGrid
from sp_plugins.core.boundary import BoundsLike, as_bounds
from sp_plugins.core.config import SPConfig
from sp_plugins.core.perturb import perturb, perturbed_mean
from sp_plugins.core.schedule import AlphaSchedule

log = logging.getLogger(__name__)

T = TypeVar("T")


class StochasticPreconditioner(nn.Module):
    """Perturbs positions while training and while alpha > 0; otherwise returns its input.

    Step it with :meth:`set_step` (a nerfstudio training callback does so every iteration).
    Its ``state_dict`` holds the step and total, so a resumed run continues at the same alpha,
    plus the alpha grid's weights when there is one.

    A training step never synchronises with an accelerator: the step, total and alpha live as
    Python numbers (the buffers only mirror them for checkpoints and are read back on load).
    With ``seed`` set, each distributed rank draws its own noise (``seed + rank``).

    Args:
        config: the shared :class:`SPConfig`.
        total_steps: length of training (resolves fractional ``end``); can be set later.
        scene_diagonal: needed when ``config.relative_to_diagonal``.
        bounds: the box for ``reflect`` / ``clamp`` and for the alpha grid.
        dim: dimension of the positions (2 for images).
    """

    def __init__(
        self,
        config: SPConfig,
        *,
        total_steps: Optional[int] = None,
        scene_diagonal: Optional[float] = None,
        bounds: Optional[BoundsLike] = None,
        dim: int = 3,
    ) -> None:
        super().__init__()
        config.validate()
        self.config = config
        self.dim = dim
        if config.relative_to_diagonal and scene_diagonal is None:
            raise ValueError("relative_to_diagonal=True needs the scene_diagonal to turn alpha0 into scene units")
        self.scene_diagonal = scene_diagonal if config.relative_to_diagonal else None
        if config.boundary != "none" and bounds is None:
            raise ValueError(f"boundary={config.boundary!r} needs the scene bounds; pass bounds or use boundary='none'")
        self._bounds = None
        if bounds is not None:
            lo, hi = as_bounds(bounds, dim, torch.zeros(()))
            self.register_buffer("bounds_lo", lo, persistent=False)
            self.register_buffer("bounds_hi", hi, persistent=False)
            self._bounds = True
        self.register_buffer("step", torch.zeros((), dtype=torch.long))
        self.register_buffer("total_steps", torch.tensor(-1 if total_steps is None else int(total_steps)))
        self._step = 0
        self._total = -1 if total_steps is None else int(total_steps)
        self._schedule: Optional[AlphaSchedule] = None
        self._schedule_key: Optional[tuple] = None
        self._alpha = 0.0
        self._generators: dict = {}
        # alpha0 in scene units, known without the schedule (whose fractional end needs the total)
        self._alpha0 = config.alpha0 * (self.scene_diagonal if self.scene_diagonal is not None else 1.0)
        self.alpha_grid: Optional[AlphaGrid] = None
        if config.alpha_grid:
            init = config.alpha_grid_init if config.alpha_grid_init is not None else self._alpha0
            if not init > 0:
                raise ValueError(
                    "alpha_grid=True needs a positive initial alpha: set alpha_grid_init or an alpha0 > 0"
                )
            self.alpha_grid = AlphaGrid(dim, config.alpha_grid_resolution, init, bounds if bounds is not None else (-1.0, 1.0))
        if total_steps is not None:
            self.set_step(0, total_steps)

    # -- schedule ---------------------------------------------------------------------------
    @property
    def schedule(self) -> AlphaSchedule:
        total = self._total
        key = (total,)
        if self._schedule is None or self._schedule_key != key:
            c = self.config
            self._schedule = AlphaSchedule.resolve(
                c.schedule,
                c.alpha0,
                end=c.end,
                total_steps=None if total < 0 else total,
                scene_diagonal=self.scene_diagonal,
                final_ratio=c.final_ratio,
            )
            self._schedule_key = key
        return self._schedule

    def set_step(self, step: int, total_steps: Optional[int] = None) -> float:
        """Move to ``step`` (of ``total_steps``) and return the alpha in force there."""
        if total_steps is not None and self._total != int(total_steps):
            self._total = int(total_steps)
            self.total_steps.fill_(self._total)
        self._step = int(step)
        self.step.fill_(self._step)  # an asynchronous fill: no host sync on an accelerator
        self._alpha = self.schedule(self._step) if self.config.enabled else 0.0
        return self._alpha

    @property
    def alpha(self) -> float:
        """The scheduled alpha at the current step (the alpha grid's scale when it is on)."""
        return self._alpha

    @property
    def active(self) -> bool:
        return self.training and self._alpha > 0.0

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self._total = int(self.total_steps)  # a sync, but only when a checkpoint loads
        self._step = int(self.step)
        if self._total >= 0 or self.config.schedule == "constant":
            self.set_step(self._step)

    # -- perturbation -----------------------------------------------------------------------
    def _generator(self, device: torch.device) -> Optional[torch.Generator]:
        if self.config.seed is None:
            return None
        key = str(device)
        if key not in self._generators:
            g = torch.Generator(device=device)
            g.manual_seed(self.config.seed + distributed_rank())
            self._generators[key] = g
        return self._generators[key]

    def alpha_at(self, x: Float[Tensor, "*batch dim"]):
        """Alpha used at ``x``: the scheduled float, or the grid's values times the schedule's
        decay (so a grid run still ends as an ordinary field)."""
        if self.alpha_grid is None:
            return self._alpha
        decay = self._alpha / self._alpha0 if self._alpha0 > 0 else 0.0
        return self.alpha_grid(x.detach()) * decay

    def _kwargs(self, x: Tensor) -> dict:
        bounds = None
        if self._bounds and self.config.boundary != "none":
            bounds = (self.bounds_lo.to(x.dtype), self.bounds_hi.to(x.dtype))
        return dict(
            noise=self.config.noise,
            boundary=self.config.boundary,
            bounds=bounds,
            generator=self._generator(x.device),
            validate=False,
        )

    def forward(self, x: Float[Tensor, "*batch dim"]) -> Float[Tensor, "*batch dim"]:
        """One perturbation of ``x`` (the input tensor itself when inactive)."""
        if not self.active:
            return x
        return perturb(x, self.alpha_at(x), **self._kwargs(x))

    def blurred(self, fn: Callable[[Tensor], Tensor], x: Float[Tensor, "*batch dim"]) -> Tensor:
        """``fn`` of the perturbed positions, averaged over ``num_samples`` draws when > 1.
        ``fn`` maps ``[*batch, dim]`` to ``[*batch, ...]`` for any leading batch shape."""
        if not self.active:
            return fn(x)
        if self.config.num_samples == 1:
            return fn(self(x))
        return perturbed_mean(fn, x, self.alpha_at(x), self.config.num_samples, **self._kwargs(x))

    def mean_over_draws(self, run_once: Callable[[], T]) -> T:
        """``run_once()`` averaged over ``num_samples`` calls while active (each call draws new
        noise through this module), else a single call. ``run_once`` returns a tensor, or a dict
        / tuple of tensors (a field's outputs); non-tensor entries are taken from the first call.
        This is how a host hook honours ``num_samples`` without knowing what the field returns."""
        k = self.config.num_samples if self.active else 1
        first = run_once()
        if k == 1:
            return first
        total = first
        for _ in range(k - 1):
            total = _add_outputs(total, run_once())
        return _scale_outputs(total, 1.0 / k)

    def extra_repr(self) -> str:
        c = self.config
        return f"enabled={c.enabled}, alpha={self._alpha:.4g}, step={self._step}/{self._total}, noise={c.noise}, boundary={c.boundary}"



def distributed_rank() -> int:
    """This process's rank in a torch.distributed job (0 outside one)."""
    dist = torch.distributed
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def _add_outputs(a, b):
    if isinstance(a, Tensor):
        return a + b if a.is_floating_point() else a
    if isinstance(a, dict):
        return {key: _add_outputs(value, b[key]) for key, value in a.items()}
    if isinstance(a, (tuple, list)):
        return type(a)(_add_outputs(u, v) for u, v in zip(a, b))
    return a


def _scale_outputs(a, factor: float):
    if isinstance(a, Tensor):
        return a * factor if a.is_floating_point() else a
    if isinstance(a, dict):
        return {key: _scale_outputs(value, factor) for key, value in a.items()}
    if isinstance(a, (tuple, list)):
        return type(a)(_scale_outputs(u, factor) for u in a)
    return a
