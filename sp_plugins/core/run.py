"""SP over one training run, as one object a plain PyTorch loop calls at fixed points.

A host adapter gets SP's lifecycle from its host (callbacks, parameter groups, checkpoints); a
research repository's own ``train.py`` has none of that. :class:`SPRun` owns all of it, in the
shape of gsplat's ``Strategy``: built once with the run's length and the scene's box, then
``step_pre`` before a step, ``sp(x)`` where the loop hands positions to its field, ``step_post``
after the optimizer, ``state_dict`` / ``load_state_dict`` with the checkpoint.
"""

from __future__ import annotations

from typing import Any, Callable, Dict, Iterator, Optional

import torch
from jaxtyping import Float
from torch import Tensor

from sp_plugins.core.alpha_grid import AlphaGrid
from sp_plugins.core.boundary import BoundsLike
from sp_plugins.core.preconditioner import StochasticPreconditioner
from sp_plugins.core.settings import SPSettings

__all__ = ["SPNotReached", "SPRun"]


class SPNotReached(RuntimeError):
    """SP was on for a step, but no position went through it: the loop never called ``sp(x)``."""


class SPRun:
    """Stochastic preconditioning over one training run: settings, schedule, noise generators, the
    optional alpha grid and its optimizer, the reach check, checkpoint state and metrics.

    Args:
        config: SP's settings (:class:`~sp_plugins.SPConfig`); ``enabled=False`` is the baseline
            (every call returns its input; the loop stays the same).
        total_steps: the run's length (resolves a fractional ``end``).
        bounds: the scene's box (needed by the ``reflect`` / ``clamp`` boundaries and the alpha grid).
        scene_diagonal: needed when ``config.relative_to_diagonal``.
        dim: dimension of the positions (2 for images).
        alpha_grid_optimizer: with a learnable alpha grid, whether :meth:`step_post` steps it with an Adam of
            its own (``config.alpha_grid_lr``). ``False``: the loop's optimizer steps it (add
            :meth:`parameters` to it as a group of its own; ``sp-fit`` does, so its checkpoints keep one optimizer).

    Examples:
        >>> import torch
        >>> from sp_plugins import SPConfig, SPRun
        >>> _ = torch.manual_seed(0)
        >>> field = torch.nn.Sequential(torch.nn.Linear(2, 64), torch.nn.ReLU(), torch.nn.Linear(64, 1))
        >>> sp = SPRun(SPConfig(alpha0=0.05, end=0.3), total_steps=200, bounds=(-1.0, 1.0), dim=2)
        >>> optimizer = torch.optim.Adam(field.parameters(), lr=1e-2)
        >>> for step in range(200):
        ...     alpha = sp.step_pre(step)               # alpha for this step
        ...     x = torch.rand(256, 2) * 2 - 1
        ...     target = (x.norm(dim=-1, keepdim=True) - 0.5).abs()
        ...     loss = (field(sp(x)) - target).pow(2).mean()   # the field sees x + alpha * noise
        ...     optimizer.zero_grad(); loss.backward(); optimizer.step()
        ...     sp.step_post(step)                      # the alpha grid's step, the reach check
        >>> sp.alpha  # annealed to 0 by 30% of training
        0.0
        >>> checkpoint = {"field": field.state_dict(), "sp": sp.state_dict()}
        >>> resumed = SPRun(SPConfig(alpha0=0.05, end=0.3), total_steps=200, bounds=(-1.0, 1.0), dim=2)
        >>> resumed.load_state_dict(checkpoint["sp"]); resumed.step_index
        199
    """

    def __init__(self, config: SPSettings, *, total_steps: int, bounds: Optional[BoundsLike] = None,
                 scene_diagonal: Optional[float] = None, dim: int = 3, alpha_grid_optimizer: bool = True) -> None:
        if int(total_steps) < 1:
            raise ValueError(f"total_steps={total_steps}: a run has at least one step")
        preconditioner = StochasticPreconditioner(config, total_steps=int(total_steps), bounds=bounds,
                                                  scene_diagonal=scene_diagonal, dim=dim)
        preconditioner.train()
        self._adopt(preconditioner, alpha_grid_optimizer=alpha_grid_optimizer, reach=None, sets_mode=True,
                    length=int(total_steps))

    @classmethod
    def over(cls, preconditioner: StochasticPreconditioner, *, reach: Optional[Callable[[int], None]] = None,
             sets_mode: bool = True, alpha_grid_optimizer: bool = True) -> "SPRun":
        """An SPRun around a preconditioner someone else keeps (a host model registers it as its submodule
        ``sp``, so its state stays in the host's checkpoints under ``sp.*``).

        Args:
            reach: the reach check to run once, after the first step with alpha > 0 (a host's, which knows
                whether its fields read the moved positions); None counts calls of :meth:`__call__`.
            sets_mode: whether :meth:`step_pre` puts the preconditioner in training mode (a host's
                ``train()`` / ``eval()`` owns the mode: its viewer renders in evaluation mode between steps).
        """
        run = cls.__new__(cls)
        run._adopt(preconditioner, alpha_grid_optimizer=alpha_grid_optimizer, reach=reach, sets_mode=sets_mode)
        return run

    def _adopt(self, preconditioner: StochasticPreconditioner, *, alpha_grid_optimizer: bool,
               reach: Optional[Callable[[int], None]], sets_mode: bool, length: Optional[int] = None) -> None:
        self.preconditioner = preconditioner
        self.optimizer: Optional[torch.optim.Optimizer] = None
        """The alpha grid's own Adam (``config.alpha_grid_lr``), stepped by :meth:`step_post`; None without a grid."""
        if preconditioner.alpha_grid is not None and alpha_grid_optimizer:
            self.optimizer = torch.optim.Adam(preconditioner.alpha_grid.parameters(), lr=preconditioner.config.alpha_grid_lr)
        self._reach = reach
        self._sets_mode = sets_mode
        self._moved = 0  # positions moved in the current step
        self._length = length  # the run's length as the loop or trainer gave it (None: the state's)
        self.reach_checked = False
        """Whether the reach check ran (once per run; a resumed run checks again)."""

    def set_length(self, total_steps: int, start: Optional[int] = None) -> None:
        """The run's length, once a host's trainer says it, and the step training starts at (a resumed run's; None:
        stay at the step the state loaded, 0 on a fresh run). It holds over a state loaded later (a host that loads
        its checkpoint after registering its callbacks): :meth:`step_pre` moves to this length again."""
        self._length = int(total_steps)
        self.preconditioner.set_step(self.step_index if start is None else int(start), self._length)

    # -- the fixed points of a training loop -------------------------------------------------
    def step_pre(self, step: int) -> float:
        """Before step ``step``: SP's alpha for it (returned), training mode (unless a host owns the mode)."""
        self._moved = 0
        if self._sets_mode:
            self.preconditioner.train()
        return self.preconditioner.set_step(int(step), self._length)

    def __call__(self, x: Float[Tensor, "*batch dim"]) -> Float[Tensor, "*batch dim"]:
        """``x`` perturbed while training and while alpha > 0 (``x`` itself otherwise)."""
        out = self.preconditioner(x)
        if out is not x:
            self._moved += 1
        return out

    def blurred(self, fn: Callable[[Tensor], Tensor], x: Float[Tensor, "*batch dim"]) -> Tensor:
        """``fn`` at the perturbed ``x``, averaged over ``config.num_samples`` draws."""
        if self.preconditioner.active and self.preconditioner.training:
            self._moved += 1
        return self.preconditioner.blurred(fn, x)

    def step_post(self, step: int) -> None:
        """After the loop's optimizer step: the alpha grid's optimizer step; after the first step with
        alpha > 0, raises :class:`SPNotReached` if no position went through :meth:`__call__` in it."""
        if self.optimizer is not None and self.preconditioner.active:
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
        if self.reach_checked or not self.preconditioner.active:  # active: training, alpha > 0
            return
        self.reach_checked = True
        if self._reach is not None:
            self._reach(step)
        elif self._moved == 0:
            raise SPNotReached(f"SP was on at step {step} (alpha {self.alpha:.3g}) but no position went through it: "
                               "hand the field sp(x) (or sp.blurred(field, x)) in place of x")

    # -- state -------------------------------------------------------------------------------
    def train(self, mode: bool = True) -> "SPRun":
        self.preconditioner.train(mode)
        return self

    def eval(self) -> "SPRun":
        """Evaluation: every call returns its input, whatever alpha is."""
        return self.train(False)

    def to(self, device: Any) -> "SPRun":
        self.preconditioner.to(device)
        return self

    def parameters(self) -> Iterator[torch.nn.Parameter]:
        """The alpha grid's parameters (none without a grid). :attr:`optimizer` steps them: keep them out of the
        loop's own optimizer."""
        return self.preconditioner.parameters()

    @property
    def config(self) -> SPSettings:
        return self.preconditioner.config

    @property
    def training(self) -> bool:
        return self.preconditioner.training

    @property
    def alpha_grid(self) -> Optional[AlphaGrid]:
        """The learnable alpha grid (``config.alpha_grid``), or None."""
        return self.preconditioner.alpha_grid

    @property
    def end_step(self) -> Optional[int]:
        """The first step at which the schedule's alpha is 0 (None: it never reaches 0)."""
        schedule = self.preconditioner.schedule
        return None if schedule is None else schedule.end_step

    @property
    def alpha(self) -> float:
        """The scheduled alpha at the current step (0 once annealed, or with SP off)."""
        return self.preconditioner.alpha

    @property
    def active(self) -> bool:
        return self.preconditioner.active

    @property
    def step_index(self) -> int:
        return int(self.preconditioner.progress[0])

    def metrics(self) -> Dict[str, float]:
        """What to log per step: ``sp_alpha`` (and the alpha grid's mean while it acts)."""
        out = {"sp_alpha": float(self.alpha)}
        grid = self.preconditioner.alpha_grid
        if grid is not None and self.active:
            with torch.no_grad():
                out["sp_alpha_grid_mean"] = float(grid.values().mean())
        return out

    def state_dict(self) -> Dict[str, Any]:
        """The step, the noise generators' states, the alpha grid and its optimizer: a resumed run
        continues at the same alpha with the same noise."""
        state: Dict[str, Any] = {"preconditioner": self.preconditioner.state_dict()}
        if self.optimizer is not None:
            state["optimizer"] = self.optimizer.state_dict()
        return state

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.preconditioner.load_state_dict(state["preconditioner"])
        if self.optimizer is not None and "optimizer" in state:
            self.optimizer.load_state_dict(state["optimizer"])
        self.reach_checked = self.step_index > 0

    def __repr__(self) -> str:
        return f"SPRun({self.preconditioner.extra_repr()})"

