"""Triplane encoding whose output is differentiable (twice) with respect to its inputs.

Three learned ``R x R`` feature planes (xy, xz, yz) are sampled bilinearly at the projections of
the point and combined by sum, product or concatenation. nerfstudio's ``TriplaneEncoding``
detaches the coordinates (and ``grid_sample`` has no double backward), so an SDF built on it gets
no input gradient and no eikonal loss; here bilinear interpolation is a gather plus a weighted
sum of plain torch ops, so first and second derivatives exist.

Coordinates: inputs in ``[0, 1]^3``; ``0`` and ``1`` are the centres of the first and last texel
(``align_corners=True`` in ``grid_sample`` terms). Outside, the border texels extend as constants.
"""

from __future__ import annotations

from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor, nn

Reduce = Literal["sum", "product", "concat"]
REDUCTIONS: tuple[str, ...] = ("sum", "product", "concat")
PLANE_AXES = ((0, 1), (0, 2), (1, 2))


def bilinear_planes(
    planes: Float[Tensor, "planes res res channels"], uv: Float[Tensor, "planes n 2"]
) -> Float[Tensor, "planes n channels"]:
    """Bilinear lookup of ``uv`` in ``[0, 1]^2`` on each plane (``plane[p, i, j]`` sits at
    ``u = i / (res - 1)``, ``v = j / (res - 1)``)."""
    n_planes, res, _, channels = planes.shape
    pos = (uv * (res - 1)).clamp(0, res - 1)
    cell = torch.floor(pos).clamp(max=res - 2)
    t = pos - cell  # in [0, 1]
    cell = cell.to(torch.int64)
    base = torch.arange(n_planes, device=uv.device)[:, None] * (res * res) + cell[..., 0] * res + cell[..., 1]
    rows = torch.stack([base, base + 1, base + res, base + res + 1], dim=1)  # [P, 4, N]
    tu, tv = t[..., 0], t[..., 1]
    weights = torch.stack([(1 - tu) * (1 - tv), (1 - tu) * tv, tu * (1 - tv), tu * tv], dim=1)  # [P, 4, N]
    feats = planes.reshape(-1, channels).index_select(0, rows.reshape(-1)).view(n_planes, 4, -1, channels)
    return (feats * weights[..., None]).sum(1)


class TriplaneEncoding(nn.Module):
    """``[..., 3] in [0,1] -> [..., channels]`` (``[..., 3 * channels]`` for ``concat``).

    Args:
        resolution: texels per side R.
        channels: features per texel C.
        reduce: ``sum`` | ``product`` | ``concat`` of the three plane features.
        init_scale: planes start ``N(0, init_scale^2)`` (``product``: ``1 + N(0, init_scale^2)``,
            so that the product starts near 1 instead of near 0).
    """

    def __init__(self, resolution: int = 64, channels: int = 16, reduce: Reduce = "sum", init_scale: float = 0.1) -> None:
        super().__init__()
        if reduce not in REDUCTIONS:
            raise ValueError(f"reduce={reduce!r} is not supported; allowed values: {', '.join(REDUCTIONS)}")
        if resolution < 2 or channels < 1:
            raise ValueError(f"resolution={resolution} must be >= 2 and channels={channels} >= 1")
        self.resolution = resolution
        self.channels = channels
        self.reduce = reduce
        self.n_input_dims = 3
        self.n_output_dims = 3 * channels if reduce == "concat" else channels
        planes = init_scale * torch.randn(3, resolution, resolution, channels)
        if reduce == "product":
            planes += 1.0
        self.planes = nn.Parameter(planes)

    def get_out_dim(self) -> int:
        return self.n_output_dims

    def forward(self, x: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch out"]:
        if x.shape[-1] != 3:
            raise ValueError(f"positions have {x.shape[-1]} coordinates; TriplaneEncoding expects 3")
        batch = x.shape[:-1]
        flat = x.reshape(-1, 3)
        uv = torch.stack([flat[:, list(axes)] for axes in PLANE_AXES])  # [3, N, 2]
        planes = self.planes if self.planes.dtype == x.dtype else self.planes.to(x.dtype)
        feats = bilinear_planes(planes, uv)  # [3, N, C]
        if self.reduce == "sum":
            out = feats.sum(0)
        elif self.reduce == "product":
            out = feats.prod(0)
        else:
            out = feats.permute(1, 0, 2).reshape(-1, 3 * self.channels)
        return out.reshape(*batch, self.n_output_dims)
