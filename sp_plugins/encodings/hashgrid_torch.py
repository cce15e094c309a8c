"""Pure-torch multiresolution hash-grid lookup with tiny-cuda-nn's semantics.

Every step is an ordinary differentiable torch op, so first and second derivatives with respect
to the positions and the table come from autograd (the eikonal loss differentiates the input
gradient once more).

Per level (see :mod:`sp_plugins.encodings.grid_levels` for the level geometry):

- ``pos = x * scale + 0.5``; the cell corner is ``floor(pos)``, the local coordinate
  ``t = pos - floor(pos)`` (``smoothstep(t) = t*t*(3 - 2t)`` for Smoothstep interpolation).
- dense levels index corner ``c`` as ``(c_0 + c_1 * res + c_2 * res^2) mod entries`` (computed in
  uint32 as tcnn does, so the ``+1`` corner at the far face wraps around like tcnn's);
- hashed levels as ``(c_0 * 1 ^ c_1 * 2654435761 ^ c_2 * 805459861) mod 2^log2_hashmap_size``.
  The table size is a power of two, so the low bits of int64 products equal tcnn's uint32 ones.
"""

from __future__ import annotations

from typing import Sequence

import torch
from jaxtyping import Float, Int
from torch import Tensor

from sp_plugins.encodings.grid_levels import HASH_PRIMES, GridLevel

_UINT32_MASK = 0xFFFFFFFF


def _combine_corners(per_dim: Tensor, op: str) -> Tensor:
    """``[L, D, 2, N]`` per-axis values -> ``[L, 2**D, N]``, combining one value per axis with
    ``op`` ('mul', 'add' or 'xor'). Corner ``k`` takes the ``+1`` side on axis ``d`` when bit
    ``D - 1 - d`` of ``k`` is set."""
    acc = per_dim[:, 0]
    for d in range(1, per_dim.shape[1]):
        right = per_dim[:, d, None]  # [L, 1, 2, N]
        left = acc[:, :, None]  # [L, K, 1, N]
        if op == "mul":
            acc = left * right
        elif op == "add":
            acc = left + right
        else:
            acc = torch.bitwise_xor(left, right)
        acc = acc.reshape(acc.shape[0], -1, acc.shape[-1])
    return acc


def corner_indices(
    cell: Int[Tensor, "levels dims n"], levels: Sequence[GridLevel], hashmap_size: int
) -> Int[Tensor, "levels corners n"]:
    """Table rows (with each level's offset) of the ``2**dims`` corners of every cell."""
    n_dims = cell.shape[1]
    device = cell.device
    hashed = [lv.hashed for lv in levels]
    n_dense = hashed.index(True) if any(hashed) else len(levels)
    if any(hashed[:n_dense]) or not all(hashed[n_dense:]):
        raise AssertionError("dense levels must precede hashed levels")  # tcnn's levels grow monotonically
    corners = torch.stack([cell, cell + 1], dim=2)  # [L, D, 2, N]
    parts = []
    if n_dense:
        strides = torch.tensor(
            [[lv.resolution**d for d in range(n_dims)] for lv in levels[:n_dense]], dtype=torch.int64, device=device
        )
        sizes = torch.tensor([lv.size for lv in levels[:n_dense]], dtype=torch.int64, device=device)
        flat = _combine_corners(corners[:n_dense] * strides[:, :, None, None], "add")
        parts.append(torch.remainder(flat & _UINT32_MASK, sizes[:, None, None]))
    if n_dense < len(levels):
        primes = torch.tensor(HASH_PRIMES[:n_dims], dtype=torch.int64, device=device)
        hashed_rows = _combine_corners(corners[n_dense:] * primes[None, :, None, None], "xor")
        parts.append(hashed_rows & (hashmap_size - 1))
    rows = parts[0] if len(parts) == 1 else torch.cat(parts, dim=0)
    offsets = torch.tensor([lv.offset for lv in levels], dtype=torch.int64, device=device)
    return rows + offsets[:, None, None]


def hashgrid_encode(
    x: Float[Tensor, "n dims"],
    table: Float[Tensor, "entries features"],
    levels: Sequence[GridLevel],
    hashmap_size: int,
    smoothstep: bool = False,
) -> Float[Tensor, "n levels_times_features"]:
    """Interpolated features of ``levels`` at ``x`` (expected in [0, 1]), concatenated level by level."""
    n, n_dims = x.shape
    num_levels = len(levels)
    n_features = table.shape[1]
    scales = torch.tensor([lv.scale for lv in levels], dtype=x.dtype, device=x.device)
    pos = x.t()[None] * scales[:, None, None] + 0.5  # [L, D, N]
    cell_f = torch.floor(pos)
    t = pos - cell_f
    if smoothstep:
        t = t * t * (3.0 - 2.0 * t)
    weights = _combine_corners(torch.stack([1.0 - t, t], dim=2), "mul")  # [L, 2^D, N]
    rows = corner_indices(cell_f.to(torch.int64), levels, hashmap_size)  # [L, 2^D, N]
    feats = table.index_select(0, rows.reshape(-1)).view(num_levels, -1, n, n_features)
    out = (feats * weights[..., None]).sum(1)  # [L, N, F]
    return out.permute(1, 0, 2).reshape(n, num_levels * n_features)
