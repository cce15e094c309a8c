"""Pure-torch multiresolution hash-grid lookup with tiny-cuda-nn's semantics.

Per level (see :mod:`sp_plugins.encodings.grid_levels` for the level geometry):

- ``pos = x * scale + 0.5``; the cell corner is ``floor(pos)``, the local coordinate
  ``t = pos - floor(pos)`` (``smoothstep(t) = t*t*(3 - 2t)`` for Smoothstep interpolation).
- dense levels index corner ``c`` as ``(c_0 + c_1 * res + c_2 * res^2) mod rows``, computed in
  uint32 as tcnn does, so the ``+1`` corner on the far face wraps around like tcnn's;
- hashed levels as ``(c_0 * 1 ^ c_1 * 2654435761 ^ c_2 * 805459861) mod 2^log2_hashmap_size``.
  The table size is a power of two, so masking int64 products gives tcnn's uint32 result.

Why it is fast on a CPU. The corner weights are ordinary autograd ops on ``[levels, 2^D, N]``
tensors (so derivatives w.r.t. ``x`` of any order come from autograd), but the table access is
three small autograd Functions that are each other's derivatives:

- ``interp(table, w)[n, l] = sum_c w[l, c, n] * table[row(l, c, n)]``   (the encoding),
- ``splat(w, g)[r] = sum_{l,c,n: row = r} w[l, c, n] * g[n, l]``        (d interp / d table),
- ``dot(table, g)[l, c, n] = <table[row(l, c, n)], g[n, l]>``           (d interp / d w),

so double backward (the eikonal loss) stays inside them. Each runs level by level, so one level's
slice of the table stays in cache, and with 2 features per level a table row is viewed as one
complex number: the gather, the weighted sum and the scatter-add (``index_add_``) then move one
8-byte element per corner instead of strided pairs. The table gradient is dense, built with one
zero fill and one ``index_add_`` per level (no sort, no ``index_put_``), and nothing is
computed for ``x`` unless ``x`` requires a gradient.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch
from jaxtyping import Float, Int
from torch import Tensor
from torch.autograd import Function

from sp_plugins.encodings.grid_levels import HASH_PRIMES, GridLevel

_UINT32_MASK = 0xFFFFFFFF


@dataclass(frozen=True)
class TableLayout:
    """Where each level's rows live in the table."""

    offsets: Tuple[int, ...]
    sizes: Tuple[int, ...]
    n_rows: int

    @staticmethod
    def of(levels: Sequence[GridLevel], n_rows: int) -> "TableLayout":
        return TableLayout(tuple(lv.offset for lv in levels), tuple(lv.size for lv in levels), n_rows)


# ------------------------------------------------------------------------------------------------
# corner rows and weights


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


def _corner_combos(per_dim: Sequence[Tensor], op, out: Tensor) -> Tensor:
    """Combine ``[2, N]`` values per axis with ``op`` (``torch.add`` or ``torch.bitwise_xor``) into
    ``out`` = ``[2**D, N]``; corner ``k`` takes the ``+1`` side on axis ``d`` when bit ``D-1-d`` is set."""
    n = out.shape[-1]
    acc = per_dim[0]
    for right in per_dim[1:-1]:
        acc = op(acc[:, None], right[None]).view(-1, n)
    if len(per_dim) == 1:
        return out.copy_(acc)
    op(acc[:, None], per_dim[-1][None], out=out.view(-1, 2, n))
    return out


def corner_indices(
    cell: Int[Tensor, "levels dims n"], levels: Sequence[GridLevel], hashmap_size: int
) -> Int[Tensor, "levels corners n"]:
    """Rows *within each level* (int32) of the ``2**dims`` corners of every cell, level by level so
    that the temporaries stay small."""
    n_levels, n_dims, n = cell.shape
    rows = torch.empty(n_levels, 2**n_dims, n, dtype=torch.int32, device=cell.device)
    mask = hashmap_size - 1
    for lvl, level in enumerate(levels):
        c = cell[lvl]  # [D, N] int64
        if level.hashed:
            # (c + 1) * p = c * p + p, and masking commutes with + and ^ on the low bits: int32 after one mask
            terms = []
            for d in range(n_dims):
                lo = (c[d] * HASH_PRIMES[d]) & mask
                terms.append(torch.stack([lo, (lo + (HASH_PRIMES[d] & mask)) & mask]).to(torch.int32))
            _corner_combos(terms, torch.bitwise_xor, rows[lvl])
        else:
            # tcnn: uint32 sum of coord * res^d, modulo the level's rows (wraps at the far face)
            terms = [torch.stack([c[d], c[d] + 1]) * level.resolution**d for d in range(n_dims)]
            flat = _corner_combos(terms, torch.add, torch.empty(2**n_dims, n, dtype=torch.int64, device=cell.device))
            rows[lvl] = torch.remainder(flat & _UINT32_MASK, level.size)
    return rows


def corner_weights(t: Sequence[Float[Tensor, "levels n"]], smoothstep: bool) -> Float[Tensor, "levels corners n"]:
    """Multilinear weights of the ``2**D`` corners from the local coordinate along each axis
    (autograd-differentiable; one tensor per axis so that backward never zero-fills a stack)."""
    acc = None
    for t_d in t:
        if smoothstep:
            t_d = t_d * t_d * (3.0 - 2.0 * t_d)
        pair = torch.stack([1.0 - t_d, t_d], dim=1)  # [L, 2, N]
        acc = pair if acc is None else (acc[:, :, None] * pair[:, None]).flatten(1, 2)
    return acc


# ------------------------------------------------------------------------------------------------
# table access kernels (no autograd inside)


def _scalar_view(table: Tensor) -> Optional[Tensor]:
    """The table as one scalar per row when that is free: real for 1 feature, complex for 2 (CPU)."""
    if table.shape[1] == 1:
        return table.view(-1)
    if table.shape[1] == 2 and table.device.type == "cpu" and table.dtype in (torch.float32, torch.float64):
        return torch.view_as_complex(table.contiguous())
    return None


def _per_level_complex(g: Tensor) -> Tensor:
    """``[N, L, 2]`` real -> ``[L, N]`` complex, contiguous (so per-level products vectorise)."""
    return torch.view_as_complex(g.contiguous()).t().contiguous()


def _interp_kernel(table: Tensor, w: Tensor, rows: Tensor, layout: TableLayout) -> Tensor:
    n_levels, n_corners, n = w.shape
    n_features = table.shape[1]
    out = table.new_empty(n_levels, n, n_features)
    scalars = _scalar_view(table)
    for lvl, (off, size) in enumerate(zip(layout.offsets, layout.sizes)):
        if scalars is not None:
            gathered = scalars[off : off + size].index_select(0, rows[lvl].view(-1)).view(n_corners, n)
            target = torch.view_as_complex(out[lvl]) if gathered.is_complex() else out[lvl, :, 0]
            torch.sum(gathered * w[lvl], 0, out=target)
        else:
            gathered = table[off : off + size].index_select(0, rows[lvl].view(-1).long()).view(n_corners, n, n_features)
            torch.sum(gathered * w[lvl][..., None], 0, out=out[lvl])
    return out.transpose(0, 1)  # [N, L, F]


def _splat_kernel(w: Tensor, g: Tensor, rows: Tensor, layout: TableLayout) -> Tensor:
    n_features = g.shape[-1]
    grad = g.new_zeros(layout.n_rows, n_features)
    scalars = _scalar_view(grad)
    if scalars is not None:
        g_lvl = _per_level_complex(g) if scalars.is_complex() else g[..., 0].t().contiguous()
        for lvl, (off, size) in enumerate(zip(layout.offsets, layout.sizes)):
            scalars[off : off + size].index_add_(0, rows[lvl].view(-1), (w[lvl] * g_lvl[lvl]).view(-1))
    else:
        for lvl, (off, size) in enumerate(zip(layout.offsets, layout.sizes)):
            src = (w[lvl][..., None] * g[None, :, lvl]).view(-1, n_features)
            grad[off : off + size].index_add_(0, rows[lvl].view(-1).long(), src)
    return grad


def _dot_kernel(table: Tensor, g: Tensor, rows: Tensor, layout: TableLayout) -> Tensor:
    n_levels, n_corners, n = rows.shape
    n_features = table.shape[1]
    out = table.new_empty(n_levels, n_corners, n)
    scalars = _scalar_view(table)
    if scalars is not None:  # complex: Re(a * conj(b)) = a.re * b.re + a.im * b.im
        g_lvl = _per_level_complex(g).conj() if scalars.is_complex() else g[..., 0].t().contiguous()
        for lvl, (off, size) in enumerate(zip(layout.offsets, layout.sizes)):
            gathered = scalars[off : off + size].index_select(0, rows[lvl].view(-1)).view(n_corners, n)
            prod = gathered * g_lvl[lvl]
            out[lvl] = prod.real if prod.is_complex() else prod
    else:
        for lvl, (off, size) in enumerate(zip(layout.offsets, layout.sizes)):
            gathered = table[off : off + size].index_select(0, rows[lvl].view(-1).long()).view(n_corners, n, n_features)
            torch.sum(gathered * g[None, :, lvl], -1, out=out[lvl])
    return out


# ------------------------------------------------------------------------------------------------
# autograd: interp, splat and dot are bilinear and each other's derivatives (any order)


class _Interp(Function):
    @staticmethod
    def forward(ctx, table, w, rows, layout):
        ctx.save_for_backward(table, w, rows)
        ctx.layout = layout
        return _interp_kernel(table, w, rows, layout)

    @staticmethod
    def backward(ctx, g):
        table, w, rows = ctx.saved_tensors
        grad_table = _Splat.apply(w, g, rows, ctx.layout) if ctx.needs_input_grad[0] else None
        grad_w = _Dot.apply(table, g, rows, ctx.layout) if ctx.needs_input_grad[1] else None
        return grad_table, grad_w, None, None


class _Splat(Function):
    @staticmethod
    def forward(ctx, w, g, rows, layout):
        ctx.save_for_backward(w, g, rows)
        ctx.layout = layout
        return _splat_kernel(w, g, rows, layout)

    @staticmethod
    def backward(ctx, grad_table):
        w, g, rows = ctx.saved_tensors
        grad_w = _Dot.apply(grad_table, g, rows, ctx.layout) if ctx.needs_input_grad[0] else None
        grad_g = _Interp.apply(grad_table, w, rows, ctx.layout) if ctx.needs_input_grad[1] else None
        return grad_w, grad_g, None, None


class _Dot(Function):
    @staticmethod
    def forward(ctx, table, g, rows, layout):
        ctx.save_for_backward(table, g, rows)
        ctx.layout = layout
        return _dot_kernel(table, g, rows, layout)

    @staticmethod
    def backward(ctx, grad_w):
        table, g, rows = ctx.saved_tensors
        grad_table = _Splat.apply(grad_w, g, rows, ctx.layout) if ctx.needs_input_grad[0] else None
        grad_g = _Interp.apply(table, grad_w, rows, ctx.layout) if ctx.needs_input_grad[1] else None
        return grad_table, grad_g, None, None


# ------------------------------------------------------------------------------------------------


def hashgrid_encode(
    x: Float[Tensor, "n dims"],
    table: Float[Tensor, "entries features"],
    levels: Sequence[GridLevel],
    hashmap_size: int,
    smoothstep: bool = False,
) -> Float[Tensor, "n levels_times_features"]:
    """Interpolated features of ``levels`` at ``x`` (expected in [0, 1]), concatenated level by level."""
    n, n_dims = x.shape
    scales = torch.tensor([lv.scale for lv in levels], dtype=x.dtype, device=x.device)[:, None]
    pos = [x[:, d][None] * scales + 0.5 for d in range(n_dims)]  # per axis [L, N]
    with torch.no_grad():
        cells = [torch.floor(p) for p in pos]
        rows = corner_indices(torch.stack(cells, dim=1).to(torch.int64), levels, hashmap_size)
    weights = corner_weights([p - c for p, c in zip(pos, cells)], smoothstep)  # [L, 2^D, N]
    out = _Interp.apply(table, weights, rows, TableLayout.of(levels, table.shape[0]))  # [N, L, F]
    return out.reshape(n, -1)
