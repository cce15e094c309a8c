"""Per-point level masking of a multiresolution encoding, guided by a level-of-detail map.

A global coarse-to-fine mask (``HashGrid.set_active_levels``) switches levels off everywhere.
Here every query gets its own number of usable levels: where a learned alpha map says the
signal is smooth (large alpha), only the coarse levels may contribute, so the fine levels'
hash-table rows are left to the detailed regions that need them (fewer collisions there). The
mask multiplies the encoding's output ``[N, levels * features]`` (coarsest level first), so it
works with any backend of :class:`~sp_plugins.encodings.HashGrid` without touching its internals.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Optional

import torch
from jaxtyping import Float
from torch import Tensor, nn


def levels_from_alpha(
    alpha: Float[Tensor, "*batch"],
    alpha_lo: float,
    alpha_hi: float,
    num_levels: int,
    min_levels: float,
) -> Float[Tensor, "*batch"]:
    """Usable levels per query: ``num_levels`` at ``alpha <= alpha_lo``, ``min_levels`` at
    ``alpha >= alpha_hi``, linear in ``log(alpha)`` between (alpha maps span decades, and a
    level's cell size falls geometrically). Fractional: the last level is partly on."""
    if not (0 < alpha_lo and math.isfinite(alpha_hi)) or not 0 < min_levels <= num_levels:
        raise ValueError(f"need 0 < alpha_lo and 0 < min_levels <= num_levels (got {alpha_lo}, {min_levels}, {num_levels})")
    span = max(math.log(alpha_hi) - math.log(alpha_lo), 1e-12)
    t = ((alpha.clamp_min(1e-30).log() - math.log(alpha_lo)) / span).clamp(0.0, 1.0)
    return num_levels - t * (num_levels - min_levels)


def level_mask(levels: Float[Tensor, " n"], num_levels: int, features_per_level: int) -> Float[Tensor, "n lf"]:
    """Mask for an encoding output laid out coarsest level first: level ``l`` gets weight
    ``clamp(levels - l, 0, 1)`` (1 for the fully usable levels, a fraction for the last one)."""
    lvl = torch.arange(num_levels, device=levels.device, dtype=levels.dtype)
    w = (levels[:, None] - lvl).clamp(0.0, 1.0)
    return w.repeat_interleave(features_per_level, dim=1)


class PerPointLevelMask(nn.Module):
    """``encoding(x) * level_mask(levels_fn(x))``; with ``levels_fn=None`` it is ``encoding(x)``.

    Args:
        encoding: a module with ``num_levels`` and ``features_per_level`` (a ``HashGrid``).
        levels_fn: maps the encoding's inputs ``[N, dim]`` to usable levels ``[N]``; set or
            replace it later (the image fit switches it on after its alpha map is learned).
    """

    def __init__(self, encoding: nn.Module, levels_fn: Optional[Callable[[Tensor], Tensor]] = None) -> None:
        super().__init__()
        self.encoding = encoding
        levelled: Any = encoding  # its attributes beyond nn.Module's (which types them Tensor | Module)
        self.num_levels = int(levelled.num_levels)
        self.features_per_level = int(levelled.features_per_level)
        self.n_output_dims = self.num_levels * self.features_per_level
        self.levels_fn = levels_fn

    def forward(self, x: Float[Tensor, "n dim"]) -> Float[Tensor, "n lf"]:
        feats = self.encoding(x)
        if self.levels_fn is None:
            return feats
        with torch.no_grad():
            mask = level_mask(self.levels_fn(x.detach()).reshape(-1).to(feats.dtype), self.num_levels, self.features_per_level)
        return feats * mask


__all__ = ["PerPointLevelMask", "level_mask", "levels_from_alpha"]
