"""ReLU field (Karnewar et al. 2022): a dense voxel grid, trilinear interpolation, then a ReLU.

The ReLU comes *after* interpolation, so a grid of raw values can carve sharp surfaces inside a
voxel. Channel 0 is density; the others are colour, either view-dependent spherical-harmonic
coefficients (3 per basis function) or plain RGB. The grid spans the scene box; positions
outside it have zero density.

Two grid layouts (``align_corners``): vertex-aligned (``True``, our default: ``n`` values per axis,
the first and last on the box faces, ``n - 1`` cells) or cell-centred (``False``, thr3ed_atom's:
``n`` cells tile the box, values at their centres; beyond the outer centres the field fades to zero,
to half the value on a face; samples never leave the box, so nothing is read further out).

Stochastic preconditioning reaches it through the one seam (:mod:`sp_plugins.nerfstudio.seam`):
``get_positions()`` returns each sample moved once (reflected into the box), before the single
grid lookup that gives both density and colour.

The grid is one ``nn.Parameter``; upsampling replaces it with a new one, which the model hands to
the optimizer (see :meth:`ReLUField.upsample_to`). Loading a checkpoint of another stage resizes
the grid in place before any gradient has been taken.
"""

from __future__ import annotations

from typing import Dict, Literal, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Float
from nerfstudio.cameras.rays import RaySamples
from nerfstudio.field_components.encodings import SHEncoding
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.base_field import Field
from torch import Tensor, nn

from sp_plugins.encodings.grid_sample import grid_sample


ColorMode = Literal["sh", "rgb"]
DIFFUSE_RGB = "rgb_diffuse"
"""Field output key of the view-independent (SH degree-0) colour."""


def color_channels(color_mode: ColorMode, sh_degree: int) -> int:
    """Grid channels that hold colour: 3 for RGB, 3 * (degree + 1)^2 for spherical harmonics."""
    if color_mode == "rgb":
        return 3
    if color_mode == "sh":
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree={sh_degree}: nerfstudio's SH basis supports degrees 0 to 3")
        return 3 * (sh_degree + 1) ** 2
    raise ValueError(f"color_mode={color_mode!r}: allowed values are 'sh' and 'rgb'")


def upsample_grid(grid: Float[Tensor, "1 c d h w"], resolution: int, align_corners: bool = True) -> Float[Tensor, "1 c r r r"]:
    """Trilinear resampling of a grid. Vertex grids (``align_corners``) going from ``n`` to
    ``2n - 1`` vertices reproduce the coarse field exactly (every new vertex lies on a coarse
    edge, face or cell centre, where trilinear interpolation is what the coarse grid renders).
    Cell grids going from ``n`` to ``2n`` cells are not exact: the new values are the coarse field
    at the new centres, but the coarse field's kinks at the old centres fall between new ones (a
    slight smoothing), and in the outer half coarse cell, where the coarse field fades to zero,
    the resampling clamps instead."""
    return F.interpolate(grid, size=(resolution,) * 3, mode="trilinear", align_corners=align_corners)


class ReLUField(Field):
    """Dense grid field: ``density = relu(trilinear(grid)[0]) * density_scale``.

    Args:
        aabb: ``[2, 3]`` box the grid spans.
        resolution: values per axis at construction (the first hierarchy stage, or the full grid):
            vertices when ``align_corners``, else cells.
        color_mode: ``sh`` (view-dependent) or ``rgb``.
        sh_degree: spherical-harmonic degree for ``sh``.
        density_scale: multiplies the rectified density (scene units^-1).
        density_init: uniform range of the initial raw density values.
        color_init: uniform range of the initial raw colour values (before the sigmoid).
        align_corners: vertex-aligned (True) or cell-centred (False, thr3ed_atom) grid.
        diffuse_output: also return the diffuse colour (SH degree-0 term only) under
            :data:`DIFFUSE_RGB`, for thr3ed_atom's diffuse-render loss (``sh`` colour only).
    """

    def __init__(
        self,
        aabb: Float[Tensor, "2 3"],
        resolution: int,
        color_mode: ColorMode = "sh",
        sh_degree: int = 1,
        density_scale: float = 1.0,
        density_init: Sequence[float] = (-1.0, 1.0),
        color_init: Sequence[float] = (-1.0, 1.0),
        align_corners: bool = True,
        diffuse_output: bool = False,
    ) -> None:
        super().__init__()
        if resolution < (2 if align_corners else 1):
            raise ValueError(f"resolution={resolution}: a vertex grid needs at least 2 vertices per axis, a cell grid 1 cell")
        if diffuse_output and color_mode != "sh":
            raise ValueError("diffuse_output needs color_mode 'sh' (the diffuse colour is the SH degree-0 term)")
        if not density_scale > 0:
            raise ValueError(f"density_scale={density_scale}: must be > 0")
        for name, (lo, hi) in (("density_init", density_init), ("color_init", color_init)):
            if not lo <= hi:
                raise ValueError(f"{name}={(lo, hi)}: give (low, high) with low <= high")
        self.color_mode = color_mode
        self.num_color = color_channels(color_mode, sh_degree)
        self.sh = SHEncoding(levels=sh_degree + 1, implementation="torch") if color_mode == "sh" else None
        self.density_scale = float(density_scale)
        self.align_corners = bool(align_corners)
        self.diffuse_output = bool(diffuse_output)
        self.register_buffer("aabb", aabb.detach().float().clone())
        grid = torch.empty(1, 1 + self.num_color, resolution, resolution, resolution)
        grid[:, :1].uniform_(*density_init)
        grid[:, 1:].uniform_(*color_init)
        self.grid = nn.Parameter(grid)

    # -- state ---------------------------------------------------------------------------------
    @property
    def resolution(self) -> int:
        return int(self.grid.shape[-1])

    @torch.no_grad()
    def upsample_to(self, resolution: int) -> nn.Parameter:
        """Resample the grid to ``resolution`` vertices per axis and return the *new* Parameter.

        A new Parameter is needed because autograd remembers a leaf's shape; the caller moves
        the optimizer over to it (:meth:`ReLUFieldBaseModel.set_stage`)."""
        if resolution != self.resolution:
            self.grid = nn.Parameter(upsample_grid(self.grid.detach(), resolution, self.align_corners).contiguous())
        return self.grid

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        saved = state_dict.get(prefix + "grid")
        if saved is not None and saved.shape != self.grid.shape:  # a checkpoint from another stage
            self.grid.data = torch.empty_like(saved, device=self.grid.device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # -- queries ---------------------------------------------------------------------------------
    def lookup(self, x: Float[Tensor, "n 3"]) -> Float[Tensor, "n channels"]:
        """Trilinear interpolation of every channel at ``x`` (zero outside the box)."""
        lo, hi = self.aabb[0], self.aabb[1]
        u = ((x - lo) / (hi - lo)) * 2.0 - 1.0
        out = grid_sample(self.grid, u.view(1, 1, 1, -1, 3), padding_mode="zeros", align_corners=self.align_corners)  # deterministic mode: by gathers on CUDA
        return out.view(self.grid.shape[1], -1).t()

    def get_density(self, ray_samples: RaySamples) -> Tuple[Tensor, Tensor]:
        shape = ray_samples.frustums.shape
        x = ray_samples.frustums.get_positions().reshape(-1, 3)
        values = self.lookup(x)
        density = F.relu(values[:, :1]) * self.density_scale
        return density.view(*shape, 1), values[:, 1:].view(*shape, self.num_color)

    def get_outputs(self, ray_samples: RaySamples, density_embedding: Optional[Tensor] = None) -> Dict[FieldHeadNames, Tensor]:
        assert density_embedding is not None
        if self.sh is None:
            return {FieldHeadNames.RGB: torch.sigmoid(density_embedding)}
        basis = self.sh(ray_samples.frustums.directions)  # [..., K]
        coeffs = density_embedding.view(*basis.shape[:-1], 3, basis.shape[-1])
        rgb = torch.sigmoid((coeffs * basis[..., None, :]).sum(-1))
        if not self.diffuse_output:
            return {FieldHeadNames.RGB: rgb}
        return {FieldHeadNames.RGB: rgb, DIFFUSE_RGB: torch.sigmoid(coeffs[..., 0] * basis[..., :1])}
