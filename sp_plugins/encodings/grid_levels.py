"""Per-level geometry of a multiresolution grid, computed exactly as tiny-cuda-nn does.

tiny-cuda-nn conventions (``include/tiny-cuda-nn/encodings/grid.h`` and ``common_device.h``),
which this module and :mod:`sp_plugins.encodings.hashgrid_torch` reproduce:

- scale of level ``l``: ``exp2(l * log2(per_level_scale)) * base_resolution - 1``, in float32.
  The ``- 1`` makes ``base_resolution`` count grid *vertices*, not cells.
- resolution (vertices per axis) of level ``l``: ``ceil(scale) + 1``.
- entries of level ``l``: ``next_multiple(resolution ** dims, 8)``, and for a hash grid at most
  ``2 ** log2_hashmap_size``. Levels are stored back to back, coarsest first; the table holds
  ``entries * features_per_level`` values, so ``table.reshape(-1)`` is tcnn's ``params`` layout.
- a level is *dense* when ``resolution ** dims <= entries`` (all coarse levels of a hash grid that
  fit in the table), otherwise it is *hashed*.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Tuple

import numpy as np

GridType = Literal["Hash", "Dense"]
GRID_TYPES: tuple[str, ...] = ("Hash", "Dense")

# tcnn's CoherentPrime hash: the first factor is 1 so that x passes through (memory coherence).
HASH_PRIMES: tuple[int, ...] = (1, 2654435761, 805459861, 3674653429, 2097192037, 1434869437, 2165219737)

_MAX_PARAMS_PER_LEVEL = (2**32 - 1) // 2  # tcnn caps a level's dense size at uint32 max / 2


@dataclass(frozen=True)
class GridLevel:
    """One level: positions map to ``x * scale + 0.5``; its rows are ``offset : offset + size``."""

    scale: float
    resolution: int
    size: int
    offset: int
    hashed: bool


def _next_multiple(value: int, multiple: int) -> int:
    return (value + multiple - 1) // multiple * multiple


def per_level_scale_from_max_resolution(base_resolution: int, max_resolution: int, num_levels: int) -> float:
    """Growth factor so that the finest level has ``max_resolution``: ``(max / base) ** (1 / (L - 1))``
    (nerfstudio's ``growth_factor``); 1 for a single level."""
    if num_levels <= 1:
        return 1.0
    return float(math.exp((math.log(max_resolution) - math.log(base_resolution)) / (num_levels - 1)))


def grid_levels(
    num_levels: int,
    n_dims: int,
    log2_hashmap_size: int,
    base_resolution: int,
    per_level_scale: float,
    grid_type: GridType = "Hash",
) -> Tuple[GridLevel, ...]:
    """Scale, resolution, table rows and dense/hashed flag of every level (tcnn arithmetic)."""
    if grid_type not in GRID_TYPES:
        raise ValueError(f"grid_type={grid_type!r} is not supported; allowed values: {', '.join(GRID_TYPES)}")
    log2_scale = np.float32(np.log2(np.float32(per_level_scale)))
    hashmap_size = 2**log2_hashmap_size
    levels = []
    offset = 0
    for level in range(num_levels):
        scale = float(np.exp2(np.float32(level) * log2_scale) * np.float32(base_resolution) - np.float32(1.0))
        resolution = int(math.ceil(scale)) + 1
        dense_size = min(resolution**n_dims, _MAX_PARAMS_PER_LEVEL)
        size = _next_multiple(dense_size, 8)
        if grid_type == "Hash":
            size = min(size, hashmap_size)
        hashed = grid_type == "Hash" and resolution**n_dims > size
        levels.append(GridLevel(scale=scale, resolution=resolution, size=size, offset=offset, hashed=hashed))
        offset += size
    return tuple(levels)
