"""What to do with perturbed positions that leave the domain.

- ``reflect``: mirror back into the box ``[lo, hi]`` as many times as needed. Reflection is
  measure-preserving, so a uniform distribution stays uniform and the blurred field near a wall
  is the field convolved with the mirrored kernel (no mass lost, none piled up).
- ``clamp``: project onto the box. Kept for comparison: it piles samples on the faces.
- ``none``: leave positions as they are (unbounded or contracted scenes).
"""

from __future__ import annotations

import contextlib
from contextvars import ContextVar
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


def as_bounds(bounds: BoundsLike, dim: int, like: Tensor, check: bool = True) -> tuple[Tensor, Tensor]:
    """Normalise ``bounds`` to two ``[dim]`` tensors on ``like``'s device and dtype.

    Accepts ``(lo, hi)`` scalars, ``(lo[dim], hi[dim])`` or a ``[2, dim]`` tensor (nerfstudio's
    ``SceneBox.aabb`` layout). ``check=False`` skips the empty-box test (a host sync on a GPU) for
    bounds that were checked once at set-up.
    """
    lo: Union[float, Tensor]
    hi: Union[float, Tensor]
    if isinstance(bounds, Tensor) and bounds.dim() == 2:
        lo, hi = bounds[0], bounds[1]
    else:
        lo, hi = bounds
    lo = torch.as_tensor(lo, device=like.device, dtype=like.dtype).expand(dim)
    hi = torch.as_tensor(hi, device=like.device, dtype=like.dtype).expand(dim)
    if check and not bool(torch.all(hi > lo)):
        raise ValueError(
            f"bounds: the box is empty (lo={lo.tolist()}, hi={hi.tolist()}); every lo must be < hi"
        )
    return lo, hi


def _fold(u: Tensor) -> tuple[Tensor, Tensor]:
    """Triangle wave of period 2 on box units ``u`` (box = [0, 1]): the folded value and whether an
    odd number of reflections happened (derivative -1)."""
    d = torch.round(u * 0.5).mul_(-2.0).add_(u)  # in [-1, 1]: |d| is the triangle wave
    return d.abs(), d < 0.0


def _origin_at(origin: Tensor, shape: torch.Size, idx: Tensor) -> Tensor:
    """The origins of the flat indices ``idx`` of a ``shape`` tensor that ``origin`` broadcasts to:
    K draws ``[K, *batch, dim]`` of ``[*batch, dim]`` origins share them (flat index mod N)."""
    if origin.shape == shape:
        return origin.reshape(-1)[idx]
    if tuple(shape[len(shape) - origin.dim():]) == tuple(origin.shape):
        return origin.reshape(-1)[idx % origin.numel()]
    return origin.expand(shape).reshape(-1)[idx]


def _per_axis(values: Tensor) -> Union[float, Tensor]:
    """A python float when every axis has the same value (a cube: scalar ops are about twice as
    fast on the CPU as broadcasting a ``[dim]`` tensor), else the tensor."""
    v = values.tolist()
    return v[0] if min(v) == max(v) else values


class _Reflect(torch.autograd.Function):
    """Fold ``y`` into the box where the original ``x`` was inside it; derivative +-1.

    Only the coordinates that left the box are folded (with a small alpha, a few percent of them),
    so the cost is one inside-test over all coordinates plus a handful of ops on the escapees; the
    backward pass keeps only the flat indices whose derivative is -1."""

    @staticmethod
    def forward(ctx, y: Tensor, origin: Optional[Tensor], lo: Tensor, hi: Tensor, sparse: bool) -> Tensor:
        if not sparse:
            return _Reflect._dense(ctx, y, origin, lo, hi)
        out = y.detach().clone(memory_format=torch.contiguous_format)
        flat = out.view(-1)
        dim = y.shape[-1]
        lo, hi = lo.expand(dim), hi.expand(dim)
        mid, half, start, width = _per_axis((lo + hi) * 0.5), _per_axis((hi - lo) * 0.5), _per_axis(lo), _per_axis(hi - lo)
        idx = ((out - mid).abs_() > half).view(-1).nonzero().squeeze(1)
        flipped = idx[:0]
        if idx.numel():
            if isinstance(width, Tensor) or isinstance(start, Tensor):  # a box that is not a cube
                axis = idx % dim
                mid, half, start, width = (
                    torch.as_tensor(v, dtype=out.dtype, device=out.device).expand(dim)[axis] for v in (mid, half, start, width)
                )  # a Python float must not become a float32 tensor: float64 boxes keep float64
            escaped = flat[idx]
            folded, flip = _fold((escaped - start) / width)
            folded = folded.mul_(width).add_(start)
            if origin is not None:  # a sample the host placed outside the box stays where it is
                keep = (_origin_at(origin.detach(), y.shape, idx) - mid).abs_() <= half
                folded = torch.where(keep, folded, escaped)
                flip &= keep
            flat[idx] = folded
            flipped = idx[flip]
        ctx.save_for_backward(flipped)
        return out

    @staticmethod
    def _dense(ctx, y: Tensor, origin: Optional[Tensor], lo: Tensor, hi: Tensor) -> Tensor:
        """Every coordinate folded, a sign mask kept: no data-dependent shapes, no host sync."""
        width = hi - lo
        folded, flip = _fold((y.detach() - lo) / width)
        out = folded.mul_(width).add_(lo)
        if origin is not None:
            keep = (origin.detach() - (lo + hi) * 0.5).abs() <= width * 0.5
            out = torch.where(keep, out, y.detach())
            flip &= keep
        ctx.dense = True
        ctx.save_for_backward(flip)
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        if getattr(ctx, "dense", False):
            (flip,) = ctx.saved_tensors
            return torch.where(flip, -grad, grad), None, None, None, None
        (flipped,) = ctx.saved_tensors
        if flipped.numel():
            grad = grad.clone(memory_format=torch.contiguous_format)
            grad.view(-1)[flipped] *= -1.0
        return grad, None, None, None, None


def reflect(
    y: Float[Tensor, "*batch dim"],
    lo: Tensor,
    hi: Tensor,
    origin: Optional[Float[Tensor, "*batch dim"]] = None,
    sparse: Optional[bool] = None,
) -> Float[Tensor, "*batch dim"]:
    """Fold ``y`` into ``[lo, hi]`` by repeated mirroring (a triangle wave of period 2 * (hi - lo)).

    With ``origin`` (the unperturbed positions, ``[*batch, dim]`` or anything that broadcasts to
    ``y``, e.g. the ``[N, dim]`` origins of ``[K, N, dim]`` draws), only coordinates whose origin lies inside the box
    are folded: a sample the host placed outside the box stays outside, for the host to treat as
    empty space. ``sparse`` folds only the coordinates that left the box (fastest on the CPU, but
    it syncs with the host); the default (:func:`sparse_fold_on`) uses it on the CPU and a dense,
    sync-free fold elsewhere."""
    lo = torch.as_tensor(lo, dtype=y.dtype, device=y.device)
    hi = torch.as_tensor(hi, dtype=y.dtype, device=y.device)
    return _Reflect.apply(y, origin, lo, hi, sparse_fold_on(y.device) if sparse is None else sparse)


_DENSE_FOLD: ContextVar[bool] = ContextVar("sp_plugins_dense_fold", default=False)


def sparse_fold_on(device: torch.device) -> bool:
    """Whether :func:`reflect` folds sparsely by default on ``device``: on the CPU only, where a host
    sync costs nothing, and nowhere inside :func:`dense_fold`."""
    return device.type == "cpu" and not _DENSE_FOLD.get()


@contextlib.contextmanager
def dense_fold():
    """Within the block (this thread or task), :func:`reflect` folds densely on every device, the
    sync-free branch a GPU takes: what counts a GPU run's syncs on a CPU runs under it."""
    token = _DENSE_FOLD.set(True)
    try:
        yield
    finally:
        _DENSE_FOLD.reset(token)


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
