"""``F.grid_sample`` (bilinear / trilinear) that stays usable under
``torch.use_deterministic_algorithms(True)``.

grid_sample's CUDA backward accumulates with atomics and has no deterministic implementation:
with the flag on, the first backward through a learned dense grid (the alpha grid, the ReLU
field) stops with a RuntimeError. :func:`grid_sample` calls ``F.grid_sample`` except in that
case (a CUDA tensor that needs a gradient, deterministic mode on, warn-only too), where it
interpolates by gathers: the same function, whose backward is an indexed accumulation that torch
runs deterministically (sorted) in that mode. Slower, so only then.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor


def deterministic_path_needed(device: torch.device, needs_grad: bool) -> bool:
    """Whether ``F.grid_sample``'s backward would be refused (or warned about) here."""
    return device.type == "cuda" and needs_grad and torch.is_grad_enabled() and torch.are_deterministic_algorithms_enabled()


def grid_sample(input: Tensor, grid: Tensor, *, padding_mode: str = "zeros", align_corners: bool = False) -> Tensor:
    """``F.grid_sample(input, grid, mode="bilinear", ...)``: ``input`` ``[N, C, (D,) H, W]``,
    ``grid`` ``[N, (D_out,) H_out, W_out, dims]`` in [-1, 1], x first. By gathers where
    :func:`deterministic_path_needed`."""
    if not deterministic_path_needed(input.device, input.requires_grad or grid.requires_grad):
        return F.grid_sample(input, grid, mode="bilinear", padding_mode=padding_mode, align_corners=align_corners)
    return grid_sample_gather(input, grid, padding_mode=padding_mode, align_corners=align_corners)


def grid_sample_gather(input: Tensor, grid: Tensor, *, padding_mode: str = "zeros", align_corners: bool = False) -> Tensor:
    """Bilinear / trilinear ``grid_sample`` with ``zeros`` or ``border`` padding as gathers and a
    weighted sum of plain torch ops (also differentiable twice)."""
    if padding_mode not in ("zeros", "border"):
        raise ValueError(f"padding_mode={padding_mode!r}: the gather path implements 'zeros' and 'border'")
    batch, channels, *spatial = input.shape
    dims = len(spatial)
    sizes = spatial[::-1]  # along x, y(, z)
    out_shape = grid.shape[1:-1]
    u = grid.reshape(batch, -1, dims)  # [N, P, dims]
    cells, fractions = [], []
    for d, s in enumerate(sizes):  # Python sizes: no tensor made from host values (a sync on CUDA)
        pos = (u[..., d] + 1.0) * (0.5 * (s - 1)) if align_corners else (u[..., d] + 1.0) * (0.5 * s) - 0.5
        if padding_mode == "border":
            pos = pos.clamp(0.0, s - 1.0)
        cell = torch.floor(pos.detach())
        fractions.append(pos - cell)
        cells.append(cell.long())
    strides = [1]
    for s in sizes[:-1]:
        strides.append(strides[-1] * s)
    flat = input.reshape(batch, channels, -1)
    out: Optional[Tensor] = None
    for corner in range(2**dims):
        index: Optional[Tensor] = None
        weight: Optional[Tensor] = None
        for d in range(dims):
            side = (corner >> d) & 1
            i = cells[d] + side
            w = fractions[d] if side else 1.0 - fractions[d]
            if padding_mode == "zeros":
                w = w * ((i >= 0) & (i < sizes[d])).to(w.dtype)
            term = i.clamp(0, sizes[d] - 1) * strides[d]
            index = term if index is None else index + term
            weight = w if weight is None else weight * w
        assert index is not None and weight is not None  # dims >= 1
        values = torch.gather(flat, 2, index[:, None, :].expand(batch, channels, index.shape[-1]))  # [N, C, P]
        contribution = values * weight[:, None, :].to(values.dtype)
        out = contribution if out is None else out + contribution
    assert out is not None  # 2**dims >= 1 corners
    return out.reshape(batch, channels, *out_shape)
