"""A learnable, spatially varying alpha (the paper's adaptive alpha maps)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence, Union

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from sp_plugins.core.boundary import BoundsLike, as_bounds


def _inverse_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


class AlphaGrid(nn.Module):
    """A positive alpha field on a 2D or 3D grid, sampled (bi/tri)linearly.

    Stored as pre-softplus logits so alpha stays positive and can shrink towards 0 smoothly.
    It learns through the reparameterisation trick: the caller perturbs with
    ``x + alpha(x) * eps`` and the task loss back-propagates into the grid. Where blurring hurts
    (fine detail) the loss pushes alpha down; where the target is smooth it barely moves.

    Args:
        dim: 2 (image) or 3 (volume).
        resolution: cells per axis, an int or one per axis (x, y[, z]).
        init: initial alpha everywhere.
        bounds: the domain mapped onto the grid, ``(lo, hi)`` or ``[2, dim]``.
    """

    def __init__(
        self,
        dim: int = 3,
        resolution: Union[int, Sequence[int]] = 128,
        init: float = 0.03,
        bounds: BoundsLike = (-1.0, 1.0),
    ) -> None:
        super().__init__()
        if dim not in (2, 3):
            raise ValueError(f"dim={dim}: an alpha grid is 2D or 3D")
        if not (math.isfinite(init) and init > 0):
            raise ValueError(f"init={init!r}: the initial alpha must be a finite number > 0")
        res = [resolution] * dim if isinstance(resolution, int) else list(resolution)
        if len(res) != dim or min(res) < 2:
            raise ValueError(f"resolution={resolution!r}: need {dim} sizes, each >= 2")
        self.dim = dim
        lo, hi = as_bounds(bounds, dim, torch.zeros(()))
        self.register_buffer("lo", lo, persistent=False)
        self.register_buffer("hi", hi, persistent=False)
        # grid_sample wants [1, C, (D,) H, W] with the last axis indexing x.
        self.logits = nn.Parameter(torch.full((1, 1, *reversed(res)), _inverse_softplus(init)))

    def forward(self, x: Float[Tensor, "*batch dim"]) -> Float[Tensor, "*batch 1"]:
        """Alpha at positions ``x`` (clamped to the grid's edge outside its bounds)."""
        batch = x.shape[:-1]
        u = (x.reshape(-1, self.dim) - self.lo) / (self.hi - self.lo) * 2.0 - 1.0
        u = u.to(self.logits.dtype).view(1, *([1] * (self.dim - 1)), -1, self.dim)
        logit = F.grid_sample(self.logits, u, mode="bilinear", padding_mode="border", align_corners=True)
        return F.softplus(logit.reshape(*batch, 1)).to(x.dtype)

    def values(self) -> Float[Tensor, "*grid"]:
        """The alpha grid itself, ``[H, W]`` or ``[D, H, W]`` (last axis is x)."""
        return F.softplus(self.logits.detach())[0, 0]

    def export(self, path: Union[str, Path], vmax: Optional[float] = None) -> Path:
        """Write the grid: a PNG colour map for 2D (row 0 at the top = smallest y), a ``.npy``
        volume for 3D. Returns the path written."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        v = self.values().cpu().numpy()
        if self.dim == 3:
            path = path.with_suffix(".npy")
            import numpy as np

            np.save(path, v)
            return path
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 5 * v.shape[0] / v.shape[1] + 0.5))
        im = ax.imshow(v, cmap="magma", vmin=0.0, vmax=vmax)
        ax.set_axis_off()
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="alpha")
        fig.savefig(path.with_suffix(".png"), dpi=120, bbox_inches="tight")
        plt.close(fig)
        return path.with_suffix(".png")
