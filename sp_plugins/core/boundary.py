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


class _Reflect(torch.autograd.Function):
    """Fold ``y`` into the box where the original ``x`` was inside it; derivative +-1.

    Written as a Function so the fold runs in place on one buffer (a broadcast ``remainder`` costs
    ten times a scalar one on the CPU) and only a sign is kept for the backward pass."""

    @staticmethod
    def forward(ctx, y: Tensor, origin: Optional[Tensor], lo: Tensor, hi: Tensor) -> Tensor:
        width = hi - lo
        u = (y.detach() - lo).div_(width)  # box -> [0, 1] per axis
        d = torch.round(u * 0.5).mul_(-2.0).add_(u)  # in [-1, 1]: |d| is the triangle wave
        flip = d < 0.0  # an odd number of reflections: the derivative is -1
        out = d.abs_().mul_(width).add_(lo)
        if origin is not None:
            inside = (origin.detach() - (lo + hi) * 0.5).abs_() <= width * 0.5
            out = torch.where(inside, out, y.detach())
            flip &= inside
        ctx.save_for_backward(flip)
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        (flip,) = ctx.saved_tensors
        return torch.where(flip, -grad, grad), None, None, None


def reflect(
    y: Float[Tensor, "*batch dim"], lo: Tensor, hi: Tensor, origin: Optional[Float[Tensor, "*batch dim"]] = None
) -> Float[Tensor, "*batch dim"]:
    """Fold ``y`` into ``[lo, hi]`` by repeated mirroring (a triangle wave of period 2 * (hi - lo)).

    With ``origin`` (the unperturbed positions), only coordinates whose origin lies inside the box
    are folded: a sample the host placed outside the box stays outside, for the host to treat as
    empty space."""
    lo = torch.as_tensor(lo, dtype=y.dtype, device=y.device)
    hi = torch.as_tensor(hi, dtype=y.dtype, device=y.device)
    return _Reflect.apply(y, origin, lo, hi)


def apply_boundary(
    y: Float[Tensor, "*batch dim"],
    kind: BoundaryKind,
    bounds: Optional[tuple[Tensor, Tensor]],
    origin: Optional[Float[Tensor, "*batch dim"]] = None,
) -> Float[Tensor, "*batch dim"]:
    """Bring perturbed positions ``y`` back into the box. Coordinates whose unperturbed ``origin``
    lies outside the box are left alone (the host decides what happens out there)."""
    check_boundary_kind(kind)
    if kind == "none":
        return y
    if bounds is None:
        raise ValueError(f"boundary={kind!r} needs bounds=(lo, hi); pass bounds or use boundary='none'")
    lo, hi = bounds
    if kind == "clamp":
        clamped = torch.maximum(torch.minimum(y, hi), lo)
        if origin is None:
            return clamped
        return torch.where((origin >= lo) & (origin <= hi), clamped, y)
    return reflect(y, lo, hi, origin)
