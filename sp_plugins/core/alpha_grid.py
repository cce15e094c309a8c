"""A learnable, spatially varying alpha (the paper's adaptive alpha maps)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, Optional, Sequence, Union

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from sp_plugins.core.boundary import BoundsLike, as_bounds
from sp_plugins.encodings.grid_sample import grid_sample

AlphaGridParameterization = Literal["log", "alpha", "softplus"]
ALPHA_GRID_PARAMETERIZATIONS: tuple[str, ...] = ("log", "alpha", "softplus")

# the state-dict key of each parameterisation: a checkpoint names how it stores alpha, so a grid
# loads any of them (converted through alpha); "logits" is the softplus grid of sp-plugins <= 0.1.0
_KEYS = {"log": "log_alpha", "alpha": "alpha", "softplus": "logits"}


def check_parameterization(kind: str) -> None:
    if kind not in ALPHA_GRID_PARAMETERIZATIONS:
        raise ValueError(
            f"alpha_grid_parameterization={kind!r} is not a parameterisation; allowed values: "
            f"{', '.join(ALPHA_GRID_PARAMETERIZATIONS)}"
        )


def _to_alpha(kind: str, raw: Tensor) -> Tensor:
    if kind == "log":
        return raw.exp()
    if kind == "alpha":
        return raw.clamp_min(0.0)
    return F.softplus(raw)


def _from_alpha(kind: str, alpha: Tensor) -> Tensor:
    if kind == "log":
        return alpha.clamp_min(1e-30).log()
    if kind == "alpha":
        return alpha.clone()
    a = alpha.clamp_min(1e-30)
    return a + torch.log(-torch.expm1(-a))  # inverse softplus


def map_figure_size(shape: Sequence[int]) -> tuple[float, float]:
    """Inches (width, height) of a 2D map ``[H, W]``'s figure: 5 wide, the grid's aspect clamped to
    [0.1, 10] (an 8 x 25611 image's map is no 16000-inch figure), plus half an inch for the margin."""
    aspect = min(max(shape[0] / shape[1], 0.1), 10.0)
    return 5.0, 5.0 * aspect + 0.5


class AlphaGrid(nn.Module):
    """A non-negative alpha field on a 2D or 3D grid, sampled (bi/tri)linearly.

    It learns through the reparameterisation trick: the caller perturbs with
    ``x + alpha(x) * eps`` and the task loss back-propagates into the grid. Where blurring hurts
    (fine detail) the loss pushes alpha down; where the target is smooth it barely moves.

    Parameterisation (what Adam moves; compared in ``docs/results/alpha-grid.md``, "Alpha grid
    parameterisation"): ``log`` (default) stores log-alpha: (1) a step of lr changes alpha by a
    factor of about ``e^lr`` whatever its scale, so one learning rate serves a scene in metres and
    an image in [0, 1]; (2) alpha never reaches 0, so no cell stops learning (a clamped cell gets no
    gradient); (3) it gives the clearest level-of-detail map on ``sp-fit image``. ``alpha`` stores
    alpha itself (the paper's words; clamped at 0 when read): a step moves it by about lr in scene
    units, so lr must scale with the initial alpha. ``softplus`` is log-alpha in all but name below
    alpha ~ 0.1.

    Checkpoints name their parameterisation by key (``log_alpha``, ``alpha``, ``logits`` for
    softplus): a grid loads any of them, converted through alpha.

    The interpolation is of the stored values, then mapped to alpha (for ``log``: geometric between
    cell centres).

    Args:
        dim: 2 (image) or 3 (volume).
        resolution: cells per axis, an int or one per axis (x, y[, z]).
        init: initial alpha everywhere (> 0).
        bounds: the domain mapped onto the grid, ``(lo, hi)`` or ``[2, dim]``.
        parameterization: ``log`` | ``alpha`` | ``softplus`` (see above).
    """

    # buffers (register_buffer below), typed here: nn.Module's attribute lookup types them Tensor | Module
    lo: Tensor
    hi: Tensor

    def __init__(
        self,
        dim: int = 3,
        resolution: Union[int, Sequence[int]] = 128,
        init: float = 0.03,
        bounds: BoundsLike = (-1.0, 1.0),
        parameterization: AlphaGridParameterization = "log",
    ) -> None:
        super().__init__()
        if dim not in (2, 3):
            raise ValueError(f"dim={dim}: an alpha grid is 2D or 3D")
        if not (math.isfinite(init) and init > 0):
            raise ValueError(f"init={init!r}: the initial alpha must be a finite number > 0")
        check_parameterization(parameterization)
        res = [resolution] * dim if isinstance(resolution, int) else list(resolution)
        if len(res) != dim or min(res) < 2:
            raise ValueError(f"resolution={resolution!r}: need {dim} sizes, each >= 2")
        self.dim = dim
        self.init = float(init)
        """The initial alpha (the preconditioner reports it, scaled, as its nominal alpha)."""
        self.parameterization = parameterization
        lo, hi = as_bounds(bounds, dim, torch.zeros(()))
        self.register_buffer("lo", lo, persistent=False)
        self.register_buffer("hi", hi, persistent=False)
        # grid_sample wants [1, C, (D,) H, W] with the last axis indexing x.
        start = _from_alpha(parameterization, torch.full((1, 1, *reversed(res)), float(init), dtype=torch.float64))
        self.register_parameter(_KEYS[parameterization], nn.Parameter(start.float()))

    @property
    def param(self) -> nn.Parameter:
        """The stored grid ``[1, 1, (D,) H, W]`` that the optimizer moves (see the class docstring)."""
        return getattr(self, _KEYS[self.parameterization])

    def forward(self, x: Float[Tensor, "*batch dim"]) -> Float[Tensor, "*batch 1"]:
        """Alpha at positions ``x`` (clamped to the grid's edge outside its bounds), in the grid's
        dtype or ``x``'s, whichever is wider (a half-precision ``x`` gets float32 alphas)."""
        batch = x.shape[:-1]
        raw = self.param
        u = (x.reshape(-1, self.dim).to(raw.dtype) - self.lo) / (self.hi - self.lo) * 2.0 - 1.0
        u = u.view(1, *([1] * (self.dim - 1)), -1, self.dim)
        sampled = grid_sample(raw, u, padding_mode="border", align_corners=True)  # deterministic mode: by gathers on CUDA
        alpha = _to_alpha(self.parameterization, sampled.reshape(*batch, 1))
        return alpha.to(torch.promote_types(x.dtype, raw.dtype))

    def values(self) -> Float[Tensor, "*grid"]:
        """The alpha grid itself, ``[H, W]`` or ``[D, H, W]`` (last axis is x), detached."""
        return _to_alpha(self.parameterization, self.param.detach())[0, 0]

    @torch.no_grad()
    def set_values(self, alpha: Float[Tensor, "*grid"]) -> None:
        """Overwrite the grid with ``alpha`` (``[H, W]`` or ``[D, H, W]``, all > 0)."""
        alpha = torch.as_tensor(alpha, dtype=torch.float64)
        if tuple(alpha.shape) != tuple(self.param.shape[2:]) or not bool((alpha > 0).all()):
            raise ValueError(f"set_values: need {tuple(self.param.shape[2:])} positive alphas, got {tuple(alpha.shape)}")
        self.param.copy_(_from_alpha(self.parameterization, alpha)[None, None])

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs):
        own = prefix + _KEYS[self.parameterization]
        if own not in state_dict:  # a grid stored in another parameterisation: convert it
            for kind, key in _KEYS.items():
                if prefix + key in state_dict:
                    stored = state_dict.pop(prefix + key)
                    alpha = _to_alpha(kind, stored.detach().to(torch.float64))
                    state_dict[own] = _from_alpha(self.parameterization, alpha).to(stored.dtype)
                    break
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)

    def extra_repr(self) -> str:
        return f"dim={self.dim}, shape={tuple(self.param.shape[2:])}, init={self.init:g}, parameterization={self.parameterization}"

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

        fig, ax = plt.subplots(figsize=map_figure_size(v.shape))
        im = ax.imshow(v, cmap="magma", vmin=0.0, vmax=vmax)
        ax.set_axis_off()
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="alpha")
        fig.savefig(path.with_suffix(".png"), dpi=120, bbox_inches="tight")
        plt.close(fig)
        return path.with_suffix(".png")
