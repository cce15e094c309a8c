"""Finite-difference gradient and Laplacian of a scalar field around already-perturbed centres.

Perturb the centre once, then evaluate every stencil point around it: all points of a stencil
share one offset, so the differences measure the (blurred) field's slope and not the noise.
"""

from __future__ import annotations

from typing import Callable, Literal, Optional, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

StencilKind = Literal["6pt", "4pt"]
STENCIL_KINDS: tuple[str, ...] = ("6pt", "4pt")


_OFFSETS: dict = {}


def check_stencil_kind(kind: str) -> None:
    """Refuse a kind that is not a stencil, in one line."""
    if kind not in STENCIL_KINDS:
        raise ValueError(f"stencil={kind!r} is not a stencil; allowed values: {', '.join(STENCIL_KINDS)}")


def stencil_offsets(kind: StencilKind, *, device=None, dtype=None) -> Float[Tensor, "points 3"]:
    """Unit offsets: ``6pt`` is +-e_i (central differences); ``4pt`` the vertices of a regular
    tetrahedron (+-1, +-1, +-1) with an even number of minus signs (length sqrt(3)).

    Made once per (kind, device, dtype) and shared (read-only): ``torch.tensor(list, device=cuda)``
    is a blocking host-to-device copy, which a training step must not pay per call."""
    key = (kind, None if device is None else torch.device(device), dtype)
    cached = _OFFSETS.get(key)
    if cached is not None:
        return cached
    check_stencil_kind(kind)
    with torch.inference_mode(False):  # a cached inference tensor could not be saved for backward later
        if kind == "6pt":
            eye = torch.eye(3, device=device, dtype=dtype)
            cached = torch.cat([eye, -eye])
        else:
            cached = torch.tensor(
                [[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]], device=device, dtype=dtype
            )
    _OFFSETS[key] = cached
    return cached


def stencil_points(
    centres: Float[Tensor, "*batch 3"], step: float, kind: StencilKind = "6pt"
) -> Float[Tensor, "*batch points 3"]:
    """Stencil points ``centre + step * offset`` for every centre."""
    offsets = stencil_offsets(kind, device=centres.device, dtype=centres.dtype)
    return centres[..., None, :] + step * offsets


def stencil_gradient(
    values: Float[Tensor, "*batch points"], step: float, kind: StencilKind = "6pt"
) -> Float[Tensor, "*batch 3"]:
    """Gradient from field values at :func:`stencil_points` (second-order accurate for ``6pt``,
    first-order for ``4pt``)."""
    offsets = stencil_offsets(kind, device=values.device, dtype=values.dtype)
    scale = 2.0 * step if kind == "6pt" else 4.0 * step
    return values @ offsets / scale


def stencil_laplacian(
    values: Float[Tensor, "*batch points"], centre_values: Float[Tensor, "*batch"], step: float, kind: StencilKind = "6pt"
) -> Float[Tensor, "*batch"]:
    """Laplacian from the stencil values and the value at the centre."""
    check_stencil_kind(kind)  # (the gradient checks through stencil_offsets)
    n = values.shape[-1]
    denom = step * step if kind == "6pt" else 2.0 * step * step
    return (values.sum(-1) - n * centre_values) / denom


def finite_differences(
    fn: Callable[[Tensor], Tensor],
    centres: Float[Tensor, "*batch 3"],
    step: float,
    kind: StencilKind = "6pt",
    centre_values: Optional[Float[Tensor, "*batch"]] = None,
) -> Tuple[Float[Tensor, "*batch 3"], Optional[Float[Tensor, "*batch"]]]:
    """Gradient (and, given the centre values, Laplacian) of a scalar field ``fn: [M, 3] -> [M]``
    or ``[M, 1]``, evaluated in one call on all stencil points."""
    pts = stencil_points(centres, step, kind)
    values = fn(pts.reshape(-1, 3)).reshape(pts.shape[:-1])
    grad = stencil_gradient(values, step, kind)
    lap = None if centre_values is None else stencil_laplacian(values, centre_values.reshape(values.shape[:-1]), step, kind)
    return grad, lap
