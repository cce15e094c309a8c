"""The module a host holds: SP config + schedule + optional alpha grid, driven by the step."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import hashlib
import logging
from typing import Any, Callable, Iterator, Optional, TypeVar, cast

import torch
from jaxtyping import Float
from torch import Tensor, nn

from sp_plugins.core.alpha_grid import AlphaGrid
from sp_plugins.core.boundary import BoundsLike, as_bounds
from sp_plugins.core.perturb import compute_dtype, perturb, perturbed_mean
from sp_plugins.core.schedule import AlphaSchedule
from sp_plugins.core.settings import SPSettings


log = logging.getLogger(__name__)

T = TypeVar("T")

_PREVIEW: contextvars.ContextVar[Optional[tuple]] = contextvars.ContextVar("sp_preview", default=None)
"""``(seed, {device: generator})`` inside :meth:`StochasticPreconditioner.preview` (per thread)."""


def previewing() -> bool:
    """True inside :meth:`StochasticPreconditioner.preview` (in this thread)."""
    return _PREVIEW.get() is not None



class StochasticPreconditioner(nn.Module):
    """Perturbs positions while training and while alpha > 0; otherwise returns its input.

    Step it with :meth:`set_step` (a nerfstudio training callback does so every iteration).
    Its ``state_dict`` holds the step and total, so a resumed run continues at the same alpha,
    plus the alpha grid's weights when there is one.

    With ``alpha_grid`` the grid gives alpha(x) (the paper's spatially adaptive variant): by
    default (``alpha_grid_mode="replace"``) the grid alone while the SP phase runs (steps before the
    schedule's end; all of training with ``schedule="constant"``), then SP is off; with
    ``"scaled"`` the grid times the schedule's decay from 1 to 0. Either way alpha0 is only the
    grid's default initial value: ``alpha0=0`` with ``alpha_grid_init`` set is a working grid run.
    A grid attached after construction (``sp.alpha_grid = AlphaGrid(...)``, the image task) is
    used the same way from the next step on.

    Positions in float16 / bfloat16 are perturbed and returned in float32 (a small alpha would be
    rounded away); an inactive preconditioner returns its input itself.

    A training step never synchronises with an accelerator: the step, total and alpha live as
    Python numbers (the buffers only mirror them for checkpoints and are read back on load).
    With ``seed`` set, each distributed rank draws its own noise (``seed + rank``).

    The noise comes from this module's own ``torch.Generator`` (one per device), and the
    generators' states are in the ``state_dict`` (its ``_extra_state``, keyed by device type and
    restored when this module next draws on a device of that type), so a run resumed from a
    checkpoint draws the same noise as one that was never interrupted. With ``seed=None`` the
    generator's seed is drawn from torch's global generator at the first draw (plus the rank), so
    an unseeded run is still random per run and still resumes to the same noise (a checkpoint
    without that state, as sp-plugins 0.1 wrote, is refused by a strict load). A state saved by another distributed rank (a multi-process run
    saves rank 0's) or under another ``seed`` is not restored: that rank starts a new stream,
    seeded from ``(seed, rank, step)`` (seeded runs) or the global generator (``seed=None``).

    Args:
        config: the shared settings (an :class:`~sp_plugins.core.config.SPConfig`).
        total_steps: length of training (resolves fractional ``end``); can be set later.
        scene_diagonal: needed when ``config.relative_to_diagonal``.
        bounds: the box for ``reflect`` / ``clamp`` and for the alpha grid.
        dim: dimension of the positions (2 for images).
    """

    # buffers (register_buffer below), typed here: nn.Module's attribute lookup types them Tensor | Module
    step: Tensor
    total_steps: Tensor

    def __init__(
        self,
        config: SPSettings,
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
        self._has_bounds = False
        if bounds is not None:
            lo, hi = as_bounds(bounds, dim, torch.zeros(()))
            self.register_buffer("bounds_lo", lo, persistent=False)
            self.register_buffer("bounds_hi", hi, persistent=False)
            self._has_bounds = True
        self.register_buffer("step", torch.zeros((), dtype=torch.long))
        self.register_buffer("total_steps", torch.tensor(-1 if total_steps is None else int(total_steps)))
        self._step = 0
        self._total = -1 if total_steps is None else int(total_steps)
        self._schedule: Optional[AlphaSchedule] = None
        self._schedule_key: Optional[tuple] = None
        self._alpha = 0.0  # the scheduled scalar at the current step
        self._grid_scale = 0.0  # the factor on an alpha grid's values at the current step
        self._decay: Optional[AlphaSchedule] = None  # the schedule's shape (alpha0 = 1)
        self._generators: dict = {}  # str(device) -> torch.Generator, built at the first draw there
        self._saved_generator_states: dict = {}  # device type -> a loaded state, applied at the next draw there
        self._reseed_at: Optional[int] = None  # set when a loaded state was another rank's or seed's
        # alpha0 in scene units, known without the schedule (whose fractional end needs the total)
        self._alpha0 = config.alpha0 * (self.scene_diagonal if self.scene_diagonal is not None else 1.0)
        self.alpha_grid: Optional[AlphaGrid] = None
        if config.alpha_grid:
            init = config.alpha_grid_init if config.alpha_grid_init is not None else self._alpha0
            if not init > 0:
                raise ValueError(
                    "alpha_grid=True needs a positive initial alpha: set alpha_grid_init or an alpha0 > 0"
                )
            self.alpha_grid = AlphaGrid(
                dim, config.alpha_grid_resolution, init, bounds if bounds is not None else (-1.0, 1.0),
                parameterization=config.alpha_grid_parameterization,
            )
        if total_steps is not None:
            self.set_step(0, total_steps)

    # -- schedule ---------------------------------------------------------------------------
    @property
    def schedule(self) -> Optional[AlphaSchedule]:
        """The schedule in force, or ``None`` while it is not known yet (a fractional ``end``
        before the step count is set). Never raises: hosts and tools read every attribute of the
        objects they walk (nerfstudio's viewer reads every attribute of the pipeline before training)."""
        try:
            return self._resolved_schedule()
        except ValueError:
            return None

    def _resolved_schedule(self) -> AlphaSchedule:
        """The schedule for the current total; raises ``ValueError`` when it cannot be resolved."""
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
            self._decay = dataclasses.replace(self._schedule, alpha0=1.0)
            self._schedule_key = key
        return self._schedule

    def set_step(self, step: int, total_steps: Optional[int] = None) -> float:
        """Move to ``step`` (of ``total_steps``) and return the alpha in force there."""
        if total_steps is not None and self._total != int(total_steps):
            self._total = int(total_steps)
            self.total_steps.fill_(self._total)
        self._step = int(step)
        self.step.fill_(self._step)  # an asynchronous fill: no host sync on an accelerator
        c = self.config
        self._alpha = self._resolved_schedule()(self._step) if c.enabled else 0.0
        # in [0, 1]; > 0 exactly before the end (the _resolved_schedule call above set _decay)
        decay = cast(AlphaSchedule, self._decay)(self._step) if c.enabled else 0.0
        self._grid_scale = decay if c.alpha_grid_mode == "scaled" else (1.0 if decay > 0.0 else 0.0)
        return self.alpha

    @property
    def alpha(self) -> float:
        """The alpha in force at the current step, 0 exactly when SP is off: the scheduled scalar,
        or with an alpha grid its nominal value ``grid_scale * init`` (what a cell still at its
        initial value gives)."""
        if self.alpha_grid is None:
            return self._alpha
        return self._grid_scale * self.alpha_grid.init

    @property
    def grid_scale(self) -> float:
        """The factor on an alpha grid's values: 1 during the SP phase and 0 after it
        (``replace``), or the schedule's decay from 1 to 0 (``scaled``)."""
        return self._grid_scale

    @property
    def progress(self) -> tuple:
        """``(step, total steps)`` as Python ints (-1: not known yet), from the mirrors of the buffers:
        no device read, so a readout may ask every step."""
        return self._step, self._total

    @property
    def scheduled(self) -> bool:
        """The schedule has SP on at the current step (alpha, or the grid's scale, above 0), training or not."""
        return self._alpha > 0.0 if self.alpha_grid is None else self._grid_scale > 0.0

    @property
    def active(self) -> bool:
        """Queries are perturbed now: :attr:`scheduled` while training (or inside :meth:`preview`)."""
        return (self.training or _PREVIEW.get() is not None) and self.scheduled

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs):
        if not any(key.startswith(prefix) for key in state_dict):
            # a pass with none of this module's entries: nothing to load, keep what an earlier pass
            # set (nerfstudio's pipeline loads its model, then itself non-strictly without the model's keys)
            super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)
            return
        self._reseed_at = None
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)
        self._total = int(self.total_steps)  # a sync, but only when a checkpoint loads
        self._step = int(self.step)
        if self.schedule is not None:  # known now (a total, a constant or an absolute end): alpha at the loaded step
            self.set_step(self._step)
        if self._reseed_at is not None:
            self._reseed_at = self._step

    # -- generator state in checkpoints ---------------------------------------------------------
    def get_extra_state(self) -> dict:
        """The noise generators' states (CPU byte tensors), keyed by device type, with the seed
        and the rank that drew them. Read only when a checkpoint is written."""
        states: dict[str, Tensor] = {}
        for key, g in self._generators.items():
            states.setdefault(torch.device(key).type, g.get_state().clone())
        for kind, state in self._saved_generator_states.items():  # loaded, not drawn from yet
            states.setdefault(kind, state)
        return {"version": 1, "seed": self.config.seed, "rank": distributed_rank(), "generators": states}

    def set_extra_state(self, state: Any) -> None:
        if not isinstance(state, dict) or not isinstance(state.get("generators"), dict):
            raise ValueError(f"the preconditioner's saved state is not a generator state (got {type(state).__name__})")
        rank = distributed_rank()
        if state.get("seed") != self.config.seed or state.get("rank", 0) != rank:
            log.info(
                "SP noise: the checkpoint's generator state (seed %s, rank %s) is not this process's "
                "(seed %s, rank %s); starting a new noise stream", state.get("seed"), state.get("rank"),
                self.config.seed, rank,
            )
            self._saved_generator_states = {}
            self._generators = {}
            self._reseed_at = self._step  # replaced by the loaded step in _load_from_state_dict
            return
        saved = {str(kind): value.detach().to("cpu", torch.uint8).clone() for kind, value in state["generators"].items()}
        for key, g in self._generators.items():  # generators already built here take theirs now
            kind = torch.device(key).type
            if kind in saved:
                g.set_state(saved.pop(kind))
        self._saved_generator_states = saved

    # -- perturbation -----------------------------------------------------------------------
    @contextlib.contextmanager
    def preview(self, seed: int = 0) -> Iterator[None]:
        """Inside the block, in this thread only, perturb as in training although the module is not
        training (the viewer's render of the field SP trains), drawing from generators of their own
        seeded ``seed``: the training noise stream, and so a resumed run, stays exactly as it was, and
        the same view shows the same blur. Every other thread (training, evaluation) is unaffected."""
        token = _PREVIEW.set((seed, {}))
        try:
            yield
        finally:
            _PREVIEW.reset(token)

    def _generator(self, device: torch.device) -> torch.Generator:
        key = str(device)
        private = _PREVIEW.get()
        if private is not None:
            seed, generators = private
            if key not in generators:
                generators[key] = torch.Generator(device=device).manual_seed(seed)
            return generators[key]
        g = self._generators.get(key)
        if g is None:
            g = torch.Generator(device=device)
            state = self._saved_generator_states.pop(torch.device(device).type, None)
            if state is not None:
                g.set_state(state)
            else:
                g.manual_seed(self._fresh_seed())
            self._generators[key] = g
        return g

    def _fresh_seed(self) -> int:
        """Seed of a generator with no saved state: ``seed + rank`` (as always), a draw from the
        global generator plus the rank with ``seed=None``, or, after a checkpoint whose state
        could not be this process's, one mixed from ``(seed, rank, step)``."""
        rank = distributed_rank()
        if self.config.seed is None:
            drawn = int(torch.empty((), dtype=torch.int64).random_())  # the CPU's global generator
            return (drawn + rank) % (1 << 63)
        if self._reseed_at is None:
            return self.config.seed + rank
        digest = hashlib.sha256(f"{self.config.seed}:{rank}:{self._reseed_at}".encode()).digest()
        return int.from_bytes(digest[:8], "little") >> 1

    def alpha_at(self, x: Float[Tensor, "*batch dim"]):
        """Alpha used at ``x``: the scheduled float, or ``[*batch, 1]`` from the alpha grid times
        :attr:`grid_scale` (1 during the SP phase in the default ``replace`` mode)."""
        if self.alpha_grid is None:
            return self._alpha
        alpha = self.alpha_grid(x.detach())
        return alpha if self._grid_scale == 1.0 else alpha * self._grid_scale

    def _kwargs(self, x: Tensor) -> dict:
        bounds = None
        if self._has_bounds and self.config.boundary != "none":
            dtype = compute_dtype(x.dtype)
            bounds = (self.bounds_lo.to(dtype), self.bounds_hi.to(dtype))
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
        return mean_of_calls(run_once, self.config.num_samples if self.active else 1)

    def extra_repr(self) -> str:
        c = self.config
        grid = f", alpha_grid={c.alpha_grid_mode} x{self._grid_scale:.4g}" if self.alpha_grid is not None else ""
        return f"enabled={c.enabled}, alpha={self.alpha:.4g}{grid}, step={self._step}/{self._total}, noise={c.noise}, boundary={c.boundary}"



def distributed_rank() -> int:
    """This process's rank in a torch.distributed job (0 outside one)."""
    dist = torch.distributed
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def mean_of_calls(run_once: Callable[[], T], k: int) -> T:
    """``run_once()`` called ``k`` times and averaged entry-wise: floating tensors (also inside a dict,
    tuple or list) are averaged, anything else is the first call's. Summed as it goes: one output
    held besides the running total."""
    first = run_once()
    if k == 1:
        return first
    total = first
    for _ in range(k - 1):
        total = _add_outputs(total, run_once())
    return _scale_outputs(total, 1.0 / k)


def _add_outputs(a, b):
    if isinstance(a, Tensor):
        return a + b if a.is_floating_point() else a
    if isinstance(a, dict):
        return {key: _add_outputs(value, b[key]) for key, value in a.items()}
    if isinstance(a, (tuple, list)):
        return _rebuilt(a, [_add_outputs(u, v) for u, v in zip(a, b)])
    return a


def _scale_outputs(a, factor: float):
    if isinstance(a, Tensor):
        return a * factor if a.is_floating_point() else a
    if isinstance(a, dict):
        return {key: _scale_outputs(value, factor) for key, value in a.items()}
    if isinstance(a, (tuple, list)):
        return _rebuilt(a, [_scale_outputs(u, factor) for u in a])
    return a


def _rebuilt(a, items: list):
    """``items`` in ``a``'s sequence type: a named tuple takes its fields as arguments."""
    return type(a)(*items) if hasattr(a, "_fields") else type(a)(items)
