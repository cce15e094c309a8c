"""MipNeRF at a configurable size.

- :class:`SPMipNerfModel`: nerfstudio's MipNeRF (the paper's sparse-view setting) whose base MLP can
  be made smaller for CPU-sized runs. SP reaches it through the one seam like any method: the moved
  origins move each conical frustum's Gaussian mean and keep its covariance, so the integrated
  encoding still low-passes what the footprint cannot resolve.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Type

from nerfstudio.models.mipnerf import MipNerfModel
from nerfstudio.models.vanilla_nerf import VanillaModelConfig

from sp_plugins.adapter import presets
from sp_plugins.core import SPConfig
from sp_plugins.nerfstudio.model import SPModel, SPModelConfig


@dataclass
class SPMipNerfModelConfig(SPModelConfig, VanillaModelConfig):
    """MipNeRF with SP on the Gaussian means."""

    _target: Type = field(default_factory=lambda: SPMipNerfModel)
    sp: SPConfig = field(default_factory=lambda: dataclasses.replace(presets.MIPNERF))
    mlp_num_layers: int = 8
    """Layers of the base MLP (MipNeRF: 8); fewer for CPU-sized runs."""
    mlp_layer_width: int = 256
    """Width of the base MLP (MipNeRF: 256)."""
    head_mlp_layer_width: int = 128
    """Width of the view-dependent colour head (MipNeRF: 128)."""

    def __post_init__(self) -> None:
        if self.mlp_num_layers < 1 or self.mlp_layer_width < 1 or self.head_mlp_layer_width < 1:
            raise ValueError("mlp_num_layers, mlp_layer_width and head_mlp_layer_width must be >= 1")


class SPMipNerfModel(SPModel, MipNerfModel):
    config: SPMipNerfModelConfig

    def populate_host_modules(self) -> None:
        super().populate_host_modules()
        c = self.config
        if (c.mlp_num_layers, c.mlp_layer_width, c.head_mlp_layer_width) != (8, 256, 128):
            # the host builds MipNeRF's 8x256 MLP unconditionally: rebuild it at the requested size
            from nerfstudio.fields.vanilla_nerf_field import NeRFField

            host = self.field
            self.field = NeRFField(
                position_encoding=host.position_encoding,
                direction_encoding=host.direction_encoding,
                base_mlp_num_layers=c.mlp_num_layers,
                base_mlp_layer_width=c.mlp_layer_width,
                head_mlp_layer_width=c.head_mlp_layer_width,
                skip_connections=(c.mlp_num_layers // 2,) if c.mlp_num_layers > 2 else (),
                use_integrated_encoding=True,
            )
