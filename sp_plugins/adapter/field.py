"""The field side of every adapter: a visible handle to the model's preconditioner.

The model owns the :class:`~sp_plugins.core.StochasticPreconditioner` (it is a submodule of
the model, so it is checkpointed once, with the model). A field that perturbs its queries holds
a :class:`PreconditionerHandle` to it: a plain attribute (``field.sp_handle``), not a submodule,
so the preconditioner is not registered a second time under the field and the field's state
dict keys stay the host's.
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Protocol, Set, TypeVar, runtime_checkable

from sp_plugins.core import StochasticPreconditioner
from sp_plugins.core.preconditioner import previewing

T = TypeVar("T")



class PreconditionerHandle:
    """A reference to a model's preconditioner that ``nn.Module`` does not register."""

    __slots__ = ("sp", "perturbed_calls", "reads", "first_move", "alpha_render")

    def __init__(self, sp: Optional[StochasticPreconditioner]) -> None:
        self.sp = sp
        self.perturbed_calls = 0
        """Field queries that were perturbed (the model checks SP reached a field while training)."""
        self.reads: Set[str] = set()
        """What the field read of the moved samples it was handed (a host seam fills it)."""
        self.first_move: Optional[Any] = None
        """The largest move of the first moved samples, a device scalar: read once, by the reach check."""
        self.alpha_render: Optional[Any] = None
        """The learned alpha grid's expected value along each ray of the field's last plain call
        (a render, not training; a host seam fills it, the model hands it on as an output)."""

    def __repr__(self) -> str:
        return (f"PreconditionerHandle({'set' if self.sp is not None else 'empty'}, perturbed_calls={self.perturbed_calls}, "
                f"reads={sorted(self.reads)})")


@runtime_checkable
class ReadPointField(Protocol):
    """A field that declares where it queries a batch of samples: SP computes its offset there.

    The one way to declare a read point, for any field class (a user's, a plugin's, ours): define
    ``sp_read_positions`` on the class, in the field's own file; no seam is edited. A host's built-in
    field classes that query elsewhere than the host's default get theirs from the host's method
    table (``READ_POINTS`` in ``sp_plugins.<host>.table``), and the seam reads both the same way."""

    def sp_read_positions(self, frustums: Any) -> Any:
        """The positions ``[*bs, 3]`` this field queries for the host's sample geometry ``frustums``."""
        ...


class SPFieldMixin:
    """Mixin for a host field that perturbs its queries; list it first among the bases."""

    sp_handle: Optional[PreconditionerHandle] = None

    def use_preconditioner(self, sp: Optional[StochasticPreconditioner]) -> None:
        """Perturb through ``sp`` (owned and checkpointed by the model, not the field)."""
        self.sp_handle = PreconditionerHandle(sp)

    @property
    def sp(self) -> Optional[StochasticPreconditioner]:
        handle = self.sp_handle
        return None if handle is None else handle.sp

    def sp_active(self) -> bool:
        """True while training with alpha > 0, the only time queries are perturbed (or inside the
        preconditioner's :meth:`~sp_plugins.core.StochasticPreconditioner.preview`, a viewer render of
        the field SP trains)."""
        sp = self.sp
        return sp is not None and (bool(getattr(self, "training", False)) or previewing()) and sp.active

    def mean_over_draws(self, run_once: Callable[[], T]) -> T:
        """``run_once()`` (which perturbs through ``self.sp``), averaged over ``num_samples`` draws
        (:meth:`StochasticPreconditioner.mean_over_draws`), and counted as one moved call."""
        assert self.sp_handle is not None and self.sp_handle.sp is not None
        if not previewing():  # a viewer render is not training: the reach check counts training calls
            self.sp_handle.perturbed_calls += 1
        return self.sp_handle.sp.mean_over_draws(run_once)
