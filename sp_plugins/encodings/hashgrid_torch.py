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

Why it is fast on a CPU (measured in ``bench/speed/hashgrid_speed.py``; what was tried and dropped is
listed in ``docs/results/hashgrid-speed.md``):

- all levels go through a handful of large ops: on a shared CPU every op pays a thread barrier,
  so op count matters as much as memory traffic;
- corner rows in int32 (each axis' hash product masked once: XOR commutes with the mask), with
  the level offsets added, so one gather / one scatter covers every level;
- forward = ``embedding_bag`` with per-corner weights: gather and weighted sum fused, no
  ``[levels, corners, N, features]`` temporary;
- table gradient = one zero fill + one ``index_add_`` (no sort, no ``index_put_``); with 2
  features a row is viewed as one complex number, so the scatter moves one 8-byte element per
  corner with a 1-D int32 index;
- nothing is computed for ``x`` unless it requires a gradient, and a pass that only wants the
  input gradient (``autograd.grad(y, x)``, the eikonal's first pass) skips the table's scatter.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor
from torch.autograd import Function

from sp_plugins.encodings.grid_levels import HASH_PRIMES, GridLevel

_UINT32_MASK = 0xFFFFFFFF


# ------------------------------------------------------------------------------------------------
# corner rows and weights


def _corner_combos(per_dim: Tensor, op, out: Tensor) -> Tensor:
    """Combine ``[L, D, 2, N]`` values (one pair per axis) with ``op`` (``torch.add`` or
    ``torch.bitwise_xor``) into ``out`` = ``[L, 2**D, N]``; corner ``k`` takes the ``+1`` side on
    axis ``d`` when bit ``D-1-d`` of ``k`` is set."""
    n_levels, n_dims, _, n = per_dim.shape
    acc = per_dim[:, 0]
    for d in range(1, n_dims - 1):
        acc = op(acc[:, :, None], per_dim[:, d, None]).view(n_levels, -1, n)
    if n_dims == 1:
        return out.copy_(acc)
    op(acc[:, :, None], per_dim[:, -1, None], out=out.view(n_levels, -1, 2, n))
    return out


class LevelConstants(NamedTuple):
    """Per-level constants of a lookup, made once on the grid's device (:func:`level_constants`),
    so a forward pass builds no tensor from Python values: ``torch.tensor(list, device=cuda)`` is
    a host-to-device copy that synchronises the host with the GPU on every call."""

    scales: Tensor  # [L] float32: tcnn's float32 scales (exact in float64 too)
    offsets: Tensor  # [L] int32: first row of each level
    strides: Tensor  # [Ld, D] int64: res**d of the dense levels
    sizes: Tensor  # [Ld] int64: rows of the dense levels
    primes: Tensor  # [D, 1] int64: tcnn's hash primes
    delta: Tensor  # [2, 1] int64: the two corners along an axis (0, 1)
    sign: Tensor  # [2, 1] float32: (-1, 1), weights (1 - t, t) = (1, 0) + sign * t

    def head(self, n_levels: int) -> "LevelConstants":
        """The constants of the ``n_levels`` coarsest levels (views, no copy)."""
        n_dense = self.sizes.shape[0]
        return self._replace(
            scales=self.scales[:n_levels], offsets=self.offsets[:n_levels],
            strides=self.strides[: min(n_dense, n_levels)], sizes=self.sizes[: min(n_dense, n_levels)],
        )


def level_constants(levels: Sequence[GridLevel], n_dims: int, device=None) -> LevelConstants:
    """The :class:`LevelConstants` of ``levels`` on ``device``."""
    dense = [lv for lv in levels if not lv.hashed]
    return LevelConstants(
        scales=torch.tensor([lv.scale for lv in levels], dtype=torch.float32, device=device),
        offsets=torch.tensor([lv.offset for lv in levels], dtype=torch.int32, device=device),
        strides=torch.tensor([[lv.resolution**d for d in range(n_dims)] for lv in dense], dtype=torch.int64, device=device).view(len(dense), n_dims),
        sizes=torch.tensor([lv.size for lv in dense], dtype=torch.int64, device=device),
        primes=torch.tensor(HASH_PRIMES[:n_dims], dtype=torch.int64, device=device)[:, None],
        delta=torch.tensor([0, 1], dtype=torch.int64, device=device)[:, None],
        sign=torch.tensor([-1.0, 1.0], dtype=torch.float32, device=device)[:, None],
    )


def corner_indices(
    cell: Int[Tensor, "levels dims n"],
    levels: Sequence[GridLevel],
    hashmap_size: int,
    constants: Optional[LevelConstants] = None,
) -> Int[Tensor, "levels corners n"]:
    """Rows *within each level* (int32) of the ``2**dims`` corners of every cell.

    All dense levels are done together, then all hashed ones: a handful of large ops, which stays
    cheap when threads are contended (every op pays a thread barrier)."""
    n_levels, n_dims, n = cell.shape
    device = cell.device
    if constants is None:
        constants = level_constants(levels, n_dims, device)
    rows = torch.empty(n_levels, 2**n_dims, n, dtype=torch.int32, device=device)
    n_dense = sum(not lv.hashed for lv in levels)
    if any(lv.hashed for lv in levels[:n_dense]):
        raise ValueError("dense levels must precede hashed levels")  # resolutions grow with the level
    delta = constants.delta  # the two corners along an axis
    if n_dense:
        # tcnn: uint32 sum of coord * res^d, modulo the level's rows (wraps at the far face)
        strides, sizes = constants.strides[:n_dense], constants.sizes[:n_dense]
        terms = (cell[:n_dense, :, None] + delta) * strides[:, :, None, None]  # [Ld, D, 2, N]
        flat = _corner_combos(terms, torch.add, torch.empty(n_dense, 2**n_dims, n, dtype=torch.int64, device=device))
        torch.remainder(flat & _UINT32_MASK, sizes[:, None, None], out=flat)
        rows[:n_dense] = flat
    if n_dense < n_levels:
        # (c + 1) * p = c * p + p, and masking commutes with + and ^ on the low bits: int32 after one mask
        mask = hashmap_size - 1
        primes = constants.primes
        low = (cell[n_dense:] * primes) & mask  # [Lh, D, N]
        terms = ((low[:, :, None] + (primes & mask)[:, :, None] * delta) & mask).to(torch.int32)  # [Lh, D, 2, N]
        _corner_combos(terms, torch.bitwise_xor, rows[n_dense:])
    return rows


def corner_weights(
    t: Float[Tensor, "levels dims n"], smoothstep: bool, sign: Optional[Tensor] = None
) -> Float[Tensor, "levels corners n"]:
    """Multilinear weights of the ``2**D`` corners from the local coordinates (autograd-differentiable;
    the axes are split with ``unbind``, whose backward stacks instead of zero-filling). ``sign``:
    the ``[2, 1]`` constant (-1, 1) (:class:`LevelConstants`), made here when not given."""
    if smoothstep:
        t = t * t * (3.0 - 2.0 * t)
    # [L, D, 2, N] = (1 - t, t) per axis in one op (a stack along dim 2 is a slow strided copy)
    if sign is None:
        sign = torch.tensor([-1.0, 1.0], device=t.device)[:, None]
    sign = sign.to(t.dtype)
    pairs = torch.addcmul((sign < 0).to(t.dtype), t[:, :, None], sign).unbind(1)  # D x [L, 2, N]
    acc = pairs[0]
    for pair in pairs[1:]:
        acc = (acc[:, :, None] * pair[:, None]).flatten(1, 2)
    return acc.contiguous()


# ------------------------------------------------------------------------------------------------
# table access kernels (no autograd inside)


def _scalar_view(table: Tensor) -> Optional[Tensor]:
    """The table as one scalar per row when that is free: real for 1 feature, complex for 2 (CPU)."""
    if table.shape[1] == 1:
        return table.view(-1)
    if table.shape[1] == 2 and table.device.type == "cpu" and table.dtype in (torch.float32, torch.float64):
        return torch.view_as_complex(table.contiguous())
    return None


# devices with a native embedding_bag; elsewhere (e.g. MPS) the forward gathers, then sums
EMBEDDING_BAG_DEVICES = {"cpu", "cuda"}
# devices whose index_select / index_add_ take int32 indices as they are (elsewhere: an int64 copy)
INT32_INDEX_DEVICES = {"cpu", "cuda"}


def _index(rows: Tensor, add_rows: bool = False) -> Tensor:
    """``rows`` flattened, int32 where the device's gather / scatter take it: no copy. The one
    exception is the CPU's ``index_add_`` of whole rows (``add_rows``), 3-5x slower with an int32
    index than with int64 (measured, torch 2.14: a 1-D scatter or a gather is as fast or faster)."""
    flat = rows.reshape(-1)
    if flat.device.type not in INT32_INDEX_DEVICES or (add_rows and flat.device.type == "cpu"):
        return flat.long()
    return flat


def _interp_kernel(table: Tensor, w: Tensor, rows: Tensor) -> Tensor:
    """``embedding_bag`` is exactly a gather fused with a weighted sum: one pass, no temporaries
    beyond the corner-last copies of ``rows`` and ``w`` it needs. Its inputs are detached (this
    runs inside an autograd Function): a table that requires grad would send it down its training
    path, which also writes per-index bookkeeping (``offset2bag``) for a backward we never call."""
    n_levels, n_corners, n = w.shape
    if table.device.type not in EMBEDDING_BAG_DEVICES:
        values = table.index_select(0, _index(rows)).view(n_levels, n_corners, n, -1)
        return torch.sum(values * w[..., None], 1).transpose(0, 1)
    bags = rows.transpose(1, 2).reshape(-1, n_corners)
    weights = w.detach().transpose(1, 2).reshape(-1, n_corners)
    out = F.embedding_bag(bags, table.detach(), per_sample_weights=weights, mode="sum")  # [L * N, F]
    return out.view(n_levels, n, -1).transpose(0, 1)  # [N, L, F]


def _dot_kernel(table: Tensor, g: Tensor, rows: Tensor) -> Tensor:
    n_levels, n_corners, n = rows.shape
    scalars = _scalar_view(table)
    if scalars is None:
        values = table.index_select(0, _index(rows)).view(n_levels, n_corners, n, -1)
        return torch.sum(values * g.transpose(0, 1)[:, None], -1)
    planes = g.permute(2, 1, 0).contiguous()  # [F, L, N]: contiguous operands vectorise
    values = scalars.index_select(0, _index(rows)).view(n_levels, n_corners, n)
    if not values.is_complex():
        return values * planes[0][:, None]
    # <a, b> over the 2 features = a.re * b.re + a.im * b.im
    values = torch.view_as_real(values)
    return torch.addcmul(values[..., 0] * planes[0][:, None], values[..., 1], planes[1][:, None])


def _splat_kernel(w: Tensor, g: Tensor, rows: Tensor, n_rows: int) -> Tensor:
    """One zero fill and one ``index_add_`` of ``w * g`` into the rows (int32, 1-D when possible)."""
    n_features = g.shape[-1]
    grad = g.new_zeros(n_rows, n_features)
    scalars = _scalar_view(grad)
    if scalars is None:
        src = (w[..., None] * g.transpose(0, 1)[:, None]).reshape(-1, n_features)
        grad.index_add_(0, _index(rows, add_rows=True), src)
    elif not scalars.is_complex():
        scalars.index_add_(0, _index(rows), (w * g[..., 0].t().contiguous()[:, None]).reshape(-1))
    else:
        g_lvl = torch.view_as_complex(g.contiguous()).t().contiguous()  # [L, N]
        src = torch.empty(w.shape, dtype=scalars.dtype, device=w.device).copy_(w)  # contiguous complex
        src.mul_(g_lvl[:, None])
        scalars.index_add_(0, _index(rows), src.view(-1))
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
    """``out[n, l] = sum_c w[l, c, n] * table[row(l, c, n)]``."""

    @staticmethod
    def forward(ctx, table, w, rows):
        ctx.save_for_backward(table, w, rows)
        return _interp_kernel(table, w, rows)

    @staticmethod
    def backward(ctx, g):
        table, w, rows = ctx.saved_tensors
        grad_table = _Splat.apply(w, g, rows, table.shape[0]) if _wanted(ctx, 0) else None
        grad_w = _Dot.apply(table, g, rows) if _wanted(ctx, 1) else None
        return grad_table, grad_w, None


class _Splat(Function):
    """``grad[r] = sum_{l,c,n: row(l,c,n) = r} w[l, c, n] * g[n, l]`` (d interp / d table)."""

    @staticmethod
    def forward(ctx, w, g, rows, n_rows):
        ctx.save_for_backward(w, g, rows)
        return _splat_kernel(w, g, rows, n_rows)

    @staticmethod
    def backward(ctx, grad_table):
        w, g, rows = ctx.saved_tensors
        grad_w = _Dot.apply(grad_table, g, rows) if _wanted(ctx, 0) else None
        grad_g = _Interp.apply(grad_table, w, rows) if _wanted(ctx, 1) else None
        return grad_w, grad_g, None, None


class _Dot(Function):
    """``out[l, c, n] = <table[row(l, c, n)], g[n, l]>`` (d interp / d w)."""

    @staticmethod
    def forward(ctx, table, g, rows):
        ctx.save_for_backward(table, g, rows)
        return _dot_kernel(table, g, rows)

    @staticmethod
    def backward(ctx, grad_w):
        table, g, rows = ctx.saved_tensors
        grad_table = _Splat.apply(grad_w, g, rows, table.shape[0]) if _wanted(ctx, 0) else None
        grad_g = _Interp.apply(table, grad_w, rows) if _wanted(ctx, 1) else None
        return grad_table, grad_g, None


# ------------------------------------------------------------------------------------------------


def hashgrid_encode(
    x: Float[Tensor, "n dims"],
    table: Float[Tensor, "entries features"],
    levels: Sequence[GridLevel],
    hashmap_size: int,
    smoothstep: bool = False,
    constants: Optional[LevelConstants] = None,
) -> Float[Tensor, "n levels_times_features"]:
    """Interpolated features of ``levels`` at ``x`` (expected in [0, 1]), concatenated level by level.

    ``constants``: :func:`level_constants` of ``levels`` on ``x``'s device (HashGrid keeps them as
    buffers); without them they are made here, which costs a host-to-device copy per call on a GPU."""
    n = x.shape[0]
    if constants is None:
        constants = level_constants(levels, x.shape[1], x.device)
    scales = constants.scales.to(x.dtype)  # float32 values: exact in float64 as well
    pos = torch.addcmul(torch.full_like(scales, 0.5)[:, None, None], x.t()[None], scales[:, None, None])  # [L, D, N]
    with torch.no_grad():
        cell = torch.floor(pos)
        rows = corner_indices(cell.to(torch.int64), levels, hashmap_size, constants)
        rows += constants.offsets[:, None, None]
    weights = corner_weights(pos - cell, smoothstep, constants.sign)  # [L, 2^D, N]
    out = _Interp.apply(table, weights, rows)  # [N, L, F]
    return out.reshape(n, -1)
