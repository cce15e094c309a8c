"""A stand-in for ``tinycudann.Encoding`` (grid encodings) that runs anywhere, slowly.

It stores its parameters exactly as tiny-cuda-nn's torch bindings do, one flat float32
``params`` Parameter, and looks them up by its own reading of tcnn's layout
(``include/tiny-cuda-nn/encodings/grid.h`` in NVlabs/tiny-cuda-nn: the level offsets of
``GridEncodingTemplated``'s constructor, ``grid_index`` and ``fast_hash``, ``pos_fract`` and the
corner loop of ``kernel_grid``). It shares no code with :mod:`sp_plugins.encodings.hashgrid_torch`,
so the two agreeing on the same ``params`` checks that our ``table`` is tcnn's layout. Written
for the tests and ``sp-gpu-check`` where tcnn cannot run: one level and one corner at a time.
"""

from __future__ import annotations

from typing import Any, List, Mapping, Optional

import numpy as np
import torch
from torch import Tensor, nn

_PRIMES = (1, 2654435761, 805459861)
_U32 = 0xFFFFFFFF


def _u32(v: Tensor) -> Tensor:
    return v & _U32


class TcnnLayoutEncoding(nn.Module):
    """``TcnnLayoutEncoding(n_input_dims, encoding_config)``, the signature of ``tinycudann.Encoding``.

    Supports ``otype`` HashGrid / DenseGrid / Grid with ``type`` Hash or Dense, Linear or
    Smoothstep interpolation, 2 or 3 input dimensions."""

    def __init__(self, n_input_dims: int, encoding_config: Mapping[str, Any], seed: int = 1337, dtype: Optional[torch.dtype] = None) -> None:
        super().__init__()
        cfg = dict(encoding_config)
        otype = cfg.get("otype", "Grid")
        self.grid_type = cfg.get("type", "Dense" if otype == "DenseGrid" else "Hash")
        self.n_levels = int(cfg.get("n_levels", 16))
        self.n_features = int(cfg.get("n_features_per_level", 2))
        self.log2_hashmap_size = int(cfg.get("log2_hashmap_size", 19))
        self.base_resolution = int(cfg.get("base_resolution", 16))
        self.per_level_scale = float(cfg.get("per_level_scale", 2.0))
        self.interpolation = cfg.get("interpolation", "Linear")
        if self.grid_type not in ("Hash", "Dense") or self.interpolation not in ("Linear", "Smoothstep") or n_input_dims not in (2, 3):
            raise ValueError(f"TcnnLayoutEncoding does not implement {dict(encoding_config)} with {n_input_dims} dims")
        self.n_input_dims = n_input_dims
        self.n_output_dims = self.n_levels * self.n_features
        self.encoding_config = dict(encoding_config)
        self.seed = seed
        # grid.h, GridEncodingTemplated(): per level, resolution**D entries, next multiple of 8,
        # at most 2**log2_hashmap_size for a hash grid; offsets are the running sum
        log2_scale = np.log2(np.float32(self.per_level_scale), dtype=np.float32)
        self.scales: List[float] = []
        self.resolutions: List[int] = []
        self.offsets: List[int] = [0]
        for level in range(self.n_levels):
            scale = np.float32(np.exp2(np.float32(level) * log2_scale, dtype=np.float32) * np.float32(self.base_resolution) - np.float32(1.0))
            resolution = int(np.ceil(scale)) + 1
            entries = min(resolution**n_input_dims, (2**32 - 1) // 2)
            entries = -(-entries // 8) * 8
            if self.grid_type == "Hash":
                entries = min(entries, 2**self.log2_hashmap_size)
            self.scales.append(float(scale))
            self.resolutions.append(resolution)
            self.offsets.append(self.offsets[-1] + entries)
        n_params = self.offsets[-1] * self.n_features
        generator = torch.Generator().manual_seed(seed)
        # the bindings' initial_params: float32, uniform in [-1e-4, 1e-4]
        self.params = nn.Parameter(torch.rand(n_params, generator=generator, dtype=torch.float32) * 2e-4 - 1e-4)

    def _entry(self, level: int, corner: Tensor) -> Tensor:
        """``grid_index`` without the feature: the entry of integer corner ``[N, D]`` in its level."""
        size = self.offsets[level + 1] - self.offsets[level]
        stride, index = 1, torch.zeros_like(corner[:, 0])
        for d in range(self.n_input_dims):
            if stride > size:  # tcnn stops accumulating once the stride passes the level's size
                break
            index = _u32(index + _u32(corner[:, d] * stride))
            stride *= self.resolutions[level]
        if self.grid_type == "Hash" and size < stride:
            index = torch.zeros_like(index)
            for d in range(self.n_input_dims):
                index = index ^ _u32(corner[:, d] * _PRIMES[d])
        return index % size

    def forward(self, x: Tensor) -> Tensor:
        x = x.to(torch.float32)
        params = self.params.to(torch.float32)
        outputs = []
        for level in range(self.n_levels):
            pos = x * self.scales[level] + 0.5  # pos_fract
            cell = torch.floor(pos)
            t = pos - cell
            if self.interpolation == "Smoothstep":
                t = t * t * (3.0 - 2.0 * t)
            cell = _u32(cell.detach().to(torch.int64))
            features = x.new_zeros(x.shape[0], self.n_features)
            for corner_id in range(2**self.n_input_dims):
                weight = x.new_ones(x.shape[0])
                corner = cell.clone()
                for d in range(self.n_input_dims):
                    if corner_id & (1 << d):
                        weight = weight * t[:, d]
                        corner[:, d] = _u32(corner[:, d] + 1)
                    else:
                        weight = weight * (1 - t[:, d])
                first = (self.offsets[level] + self._entry(level, corner)) * self.n_features
                values = params[first[:, None] + torch.arange(self.n_features, device=x.device)]
                features = features + weight[:, None] * values
            outputs.append(features)
        return torch.cat(outputs, dim=-1)
