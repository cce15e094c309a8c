"""Pure-torch multiresolution hash-grid lookup with tiny-cuda-nn's semantics.

Per level (see :mod:`sp_plugins.encodings.grid_levels` for the level geometry):

- ``pos = x * scale + 0.5``; the cell corner is ``floor(pos)``, the local coordinate
  ``t = pos - floor(pos)`` (``smoothstep(t) = t*t*(3 - 2t)`` for Smoothstep interpolation).
- dense levels index corner ``c`` as ``(c_0 + c_1 * res + c_2 * res^2) mod rows``, computed in
  uint32 as tcnn does, so the ``+1`` corner on the far face wraps around like tcnn's;
- hashed levels as ``(c_0 * 1 ^ c_1 * 2654435761 ^ c_2 * 805459861) mod 2^log2_hashmap_size``.
  The table size is a power of two, so masking int64 products gives tcnn's uint32 result.

How derivatives work. The corner weights are ordinary autograd ops on ``[levels, 2^D, N]``
tensors, so derivatives w.r.t. ``x`` of any order come from autograd. The table access is three
small autograd Functions that are each other's derivatives, so any order works there too (the
eikonal loss needs the second):

- ``interp(table, w)[n, l] = sum_c w[l, c, n] * table[row(l, c, n)]``   (the encoding),
- ``splat(w, g)[r] = sum_{l,c,n: row = r} w[l, c, n] * g[n, l]``        (d interp / d table),
- ``dot(table, g)[l, c, n] = <table[row(l, c, n)], g[n, l]>``           (d interp / d w).

Why it is fast on a CPU (measured in ``bench/hashgrid_speed.py``):

- level by level, so one level's slice of the table and all temporaries stay small and cached;
- with 2 features per level a table row is viewed as one complex number: gather, weighted sum
  and scatter-add (``index_add_`` with int32 rows) move one 8-byte element per corner;
- corner rows in int32, each axis' hash product masked once (XOR commutes with the mask);
- the table gradient is one zero fill plus one ``index_add_`` per level (no sort, no
  ``index_put_``); nothing is computed for ``x`` unless it requires a gradient, and a pass that
  only wants the input gradient (``autograd.grad(y, x)``) skips the table's scatter;
- when ``x`` requires a gradient the gathered corner values are kept (one ``[L, 2^D, N]`` tensor)
  and reused by the backward passes instead of gathered again.
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


def _per_level(g: Tensor, scalars: Optional[Tensor]) -> Tensor:
    """``[N, L, F]`` real -> ``[L, N]`` (complex for 2 features, real for 1) or ``[L, N, F]``, contiguous."""
    if scalars is None:
        return g.transpose(0, 1).contiguous()
    if scalars.is_complex():
        return torch.view_as_complex(g.contiguous()).t().contiguous()
    return g[..., 0].t().contiguous()


class _Gather:
    """Corner values ``table[rows]`` level by level; optionally all of them kept for reuse (the
    eikonal's backward passes read the same values three times)."""

    def __init__(self, table: Tensor, rows: Tensor, layout: TableLayout, cache: Optional[Tensor] = None):
        self.table, self.rows, self.layout = table, rows, layout
        self.scalars = _scalar_view(table)
        self.cache = cache

    def fill_cache(self) -> Tensor:
        n_levels, n_corners, n = self.rows.shape
        shape = (n_levels, n_corners, n) if self.scalars is not None else (n_levels, n_corners, n, self.table.shape[1])
        dtype = self.scalars.dtype if self.scalars is not None else self.table.dtype
        cache = torch.empty(shape, dtype=dtype, device=self.table.device)
        for lvl in range(n_levels):
            self.level(lvl, out=cache[lvl])
        self.cache = cache
        return cache

    def level(self, lvl: int, out: Optional[Tensor] = None) -> Tensor:
        if self.cache is not None:
            return self.cache[lvl]
        off, size = self.layout.offsets[lvl], self.layout.sizes[lvl]
        n_corners, n = self.rows.shape[1:]
        if self.scalars is not None:
            flat = None if out is None else out.view(-1)
            return torch.index_select(self.scalars[off : off + size], 0, self.rows[lvl].view(-1), out=flat).view(n_corners, n)
        flat = None if out is None else out.view(-1, self.table.shape[1])
        idx = self.rows[lvl].view(-1).long()  # 2-D index_add_/index_select are much faster with int64
        return torch.index_select(self.table[off : off + size], 0, idx, out=flat).view(n_corners, n, -1)


def _interp_kernel(gather: _Gather, w: Tensor) -> Tensor:
    n_levels, _, n = w.shape
    out = gather.table.new_empty(n_levels, n, gather.table.shape[1])
    for lvl in range(n_levels):
        values = gather.level(lvl)
        if gather.scalars is None:
            torch.sum(values * w[lvl][..., None], 0, out=out[lvl])
        else:
            target = torch.view_as_complex(out[lvl]) if values.is_complex() else out[lvl, :, 0]
            torch.sum(values * w[lvl], 0, out=target)
    return out.transpose(0, 1)  # [N, L, F]


def _dot_kernel(gather: _Gather, g: Tensor) -> Tensor:
    n_levels, n_corners, n = gather.rows.shape
    out = gather.table.new_empty(n_levels, n_corners, n)
    g_lvl = _per_level(g, gather.scalars)
    if gather.scalars is not None and gather.scalars.is_complex():
        g_lvl = g_lvl.conj()  # Re(a * conj(b)) = a.re * b.re + a.im * b.im
    for lvl in range(n_levels):
        prod = gather.level(lvl) * g_lvl[lvl]
        if gather.scalars is None:
            torch.sum(prod, -1, out=out[lvl])
        else:
            out[lvl] = prod.real if prod.is_complex() else prod
    return out


def _splat_kernel(w: Tensor, g: Tensor, rows: Tensor, layout: TableLayout) -> Tensor:
    n_features = g.shape[-1]
    grad = g.new_zeros(layout.n_rows, n_features)
    scalars = _scalar_view(grad)
    g_lvl = _per_level(g, scalars)
    for lvl, (off, size) in enumerate(zip(layout.offsets, layout.sizes)):
        if scalars is not None:
            scalars[off : off + size].index_add_(0, rows[lvl].view(-1), (w[lvl] * g_lvl[lvl]).view(-1))
        else:
            src = (w[lvl][..., None] * g_lvl[lvl][None]).view(-1, n_features)
            grad[off : off + size].index_add_(0, rows[lvl].view(-1).long(), src)
    return grad


# ------------------------------------------------------------------------------------------------
# autograd: interp, splat and dot are bilinear and each other's derivatives (any order)


def _wanted(ctx, i: int) -> bool:
    """Whether this backward pass needs the gradient of input ``i``. ``needs_input_grad`` only says
    the input requires grad; ``autograd.grad(y, x)`` (the eikonal's first pass) does not want the
    table's gradient, and asking the engine saves a whole scatter-add over the table."""
    if not ctx.needs_input_grad[i]:
        return False
    try:
        node = ctx.next_functions[i][0]
        return node is None or bool(torch._C._will_engine_execute_node(node))
    except (AttributeError, RuntimeError):  # private API: if it moves, compute everything
        return True


class _Interp(Function):
    """``out[n, l] = sum_c w[l, c, n] * table[row(l, c, n)]``. ``cache`` (optional) holds
    ``table[rows]`` already gathered; it is kept when ``w`` needs a gradient."""

    @staticmethod
    def forward(ctx, table, w, rows, layout, cache):
        gather = _Gather(table, rows, layout, cache)
        if cache is None and ctx.needs_input_grad[1]:
            cache = gather.fill_cache()
        ctx.save_for_backward(table, w, rows, cache)
        ctx.layout = layout
        return _interp_kernel(gather, w)

    @staticmethod
    def backward(ctx, g):
        table, w, rows, cache = ctx.saved_tensors
        grad_table = _Splat.apply(w, g, rows, ctx.layout) if _wanted(ctx, 0) else None
        grad_w = _Dot.apply(table, g, rows, ctx.layout, cache) if _wanted(ctx, 1) else None
        return grad_table, grad_w, None, None, None


class _Splat(Function):
    """``grad[r] = sum_{l,c,n: row(l,c,n) = r} w[l, c, n] * g[n, l]`` (d interp / d table)."""

    @staticmethod
    def forward(ctx, w, g, rows, layout):
        ctx.save_for_backward(w, g, rows)
        ctx.layout = layout
        return _splat_kernel(w, g, rows, layout)

    @staticmethod
    def backward(ctx, grad_table):
        w, g, rows = ctx.saved_tensors
        grad_w = _Dot.apply(grad_table, g, rows, ctx.layout, None) if _wanted(ctx, 0) else None
        grad_g = _Interp.apply(grad_table, w, rows, ctx.layout, None) if _wanted(ctx, 1) else None
        return grad_w, grad_g, None, None


class _Dot(Function):
    """``out[l, c, n] = <table[row(l, c, n)], g[n, l]>`` (d interp / d w)."""

    @staticmethod
    def forward(ctx, table, g, rows, layout, cache):
        ctx.save_for_backward(table, g, rows, cache)
        ctx.layout = layout
        return _dot_kernel(_Gather(table, rows, layout, cache), g)

    @staticmethod
    def backward(ctx, grad_w):
        table, g, rows, cache = ctx.saved_tensors
        grad_table = _Splat.apply(grad_w, g, rows, ctx.layout) if _wanted(ctx, 0) else None
        grad_g = _Interp.apply(table, grad_w, rows, ctx.layout, cache) if _wanted(ctx, 1) else None
        return grad_table, grad_g, None, None, None


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
    out = _Interp.apply(table, weights, rows, TableLayout.of(levels, table.shape[0]), None)  # [N, L, F]
    return out.reshape(n, -1)
