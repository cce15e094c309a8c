"""What to do with perturbed positions that leave the domain.

- ``reflect``: mirror back into the box ``[lo, hi]`` as many times as needed. Reflection is
  measure-preserving, so a uniform distribution stays uniform and the blurred field near a wall
  is the field convolved with the mirrored kernel (no mass lost, none piled up).
- ``clamp``: project onto the box. Kept for comparison: it piles samples on the faces.
- ``none``: leave positions as they are (unbounded or contracted scenes).
"""

from __future__ import annotations

from typing import Literal, Optional, Tuple, Union

import torch
from jaxtyping import Float
from torch import Tensor

BoundaryKind = Literal["reflect", "clamp", "none"]
BOUNDARY_KINDS: tuple[str, ...] = ("reflect", "clamp", "none")

BoundsLike = Union[Tuple[float, float], Tuple[Tensor, Tensor], Tensor]


def check_boundary_kind(kind: str) -> None:
    if kind not in BOUNDARY_KINDS:
        raise ValueError(
            f"boundary={kind!r} is not a boundary kind; allowed values: {', '.join(BOUNDARY_KINDS)}"
        )


def as_bounds(bounds: BoundsLike, dim: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Normalise ``bounds`` to two ``[dim]`` tensors on ``like``'s device and dtype.

    Accepts ``(lo, hi)`` scalars, ``(lo[dim], hi[dim])`` or a ``[2, dim]`` tensor (nerfstudio's
    ``SceneBox.aabb`` layout).
    """
    if isinstance(bounds, Tensor) and bounds.dim() == 2:
        lo, hi = bounds[0], bounds[1]
    else:
        lo, hi = bounds
    lo = torch.as_tensor(lo, device=like.device, dtype=like.dtype).expand(dim)
    hi = torch.as_tensor(hi, device=like.device, dtype=like.dtype).expand(dim)
    if not bool(torch.all(hi > lo)):
        raise ValueError(
            f"bounds: the box is empty (lo={lo.tolist()}, hi={hi.tolist()}); every lo must be < hi"
        )
    return lo, hi


def reflect(x: Float[Tensor, "*batch dim"], lo: Tensor, hi: Tensor) -> Float[Tensor, "*batch dim"]:
    """Fold ``x`` into ``[lo, hi]`` by repeated mirroring (a triangle wave of period 2 * (hi - lo))."""
    width = hi - lo
    t = torch.remainder(x - lo, 2.0 * width)
    return hi - (t - width).abs()


def apply_boundary(
    x: Float[Tensor, "*batch dim"], kind: BoundaryKind, bounds: Optional[tuple[Tensor, Tensor]]
) -> Float[Tensor, "*batch dim"]:
    check_boundary_kind(kind)
    if kind == "none":
        return x
    if bounds is None:
        raise ValueError(f"boundary={kind!r} needs bounds=(lo, hi); pass bounds or use boundary='none'")
    lo, hi = bounds
    if kind == "clamp":
        return torch.maximum(torch.minimum(x, hi), lo)
    return reflect(x, lo, hi)
