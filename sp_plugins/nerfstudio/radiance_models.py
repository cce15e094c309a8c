"""nerfstudio's radiance models with the shared SP settings.

- :class:`SPMipNerfModel`: SP on the mean of each conical frustum's Gaussian
  (:mod:`sp_plugins.nerfstudio.mipnerf`); the paper's sparse-view setting.
- :class:`SPNeRFModel` (vanilla NeRF), :class:`SPNerfactoModel`, :class:`SPTensoRFModel`: SP
  through ``Frustums.offsets`` on the field that renders (:mod:`sp_plugins.nerfstudio.frustum_sp`).
  Proposal networks and coarse density queries that only place samples see the plain field.

Each is the host model with :class:`~sp_plugins.nerfstudio.model.SPModel` in front; with
``sp.enabled=False`` it trains exactly like the host.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Type

from nerfstudio.fields.nerfacto_field import NerfactoField
from nerfstudio.fields.tensorf_field import TensoRFField
from nerfstudio.fields.vanilla_nerf_field import NeRFField
from nerfstudio.models.mipnerf import MipNerfModel
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.models.tensorf import TensoRFModel, TensoRFModelConfig
from nerfstudio.models.vanilla_nerf import NeRFModel, VanillaModelConfig

from sp_plugins.adapter import presets
from sp_plugins.core import SPConfig
from sp_plugins.nerfstudio.errors import InputError
from sp_plugins.nerfstudio.frustum_sp import FrustumSPField
from sp_plugins.nerfstudio.mipnerf import SPNeRFField
from sp_plugins.patches.nerfstudio_host_fields import host_builds
from sp_plugins.nerfstudio.model import SPModel, SPModelConfig

log = logging.getLogger(__name__)

MIPNERF_SP = presets.MIPNERF
POSITION_FIELD_SP = presets.POSITION_FIELD


@dataclass
class SPMipNerfModelConfig(SPModelConfig, VanillaModelConfig):
    """MipNeRF with SP on the Gaussian means."""

    _target: Type = field(default_factory=lambda: SPMipNerfModel)
    sp: SPConfig = field(default_factory=lambda: dataclasses.replace(MIPNERF_SP))
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

    def populate_modules(self) -> None:
        with host_builds("nerfstudio.models.mipnerf", SPNeRFField):
            super().populate_modules()

    def attach_sp(self) -> None:
        c = self.config
        if (c.mlp_num_layers, c.mlp_layer_width, c.head_mlp_layer_width) != (8, 256, 128):
            # the host builds MipNeRF's 8x256 MLP unconditionally: rebuild it at the requested size
            host = self.field
            self.field = SPNeRFField(
                position_encoding=host.position_encoding,
                direction_encoding=host.direction_encoding,
                base_mlp_num_layers=c.mlp_num_layers,
                base_mlp_layer_width=c.mlp_layer_width,
                head_mlp_layer_width=c.head_mlp_layer_width,
                skip_connections=(c.mlp_num_layers // 2,) if c.mlp_num_layers > 2 else (),
                use_integrated_encoding=True,
            )
        self.field.use_preconditioner(self.sp)


@dataclass
class SPNeRFModelConfig(SPModelConfig, VanillaModelConfig):
    """Vanilla NeRF (coarse and fine fields) with SP through frustum offsets."""

    _target: Type = field(default_factory=lambda: SPNeRFModel)
    sp: SPConfig = field(default_factory=lambda: dataclasses.replace(POSITION_FIELD_SP))


class SPPositionNeRFField(FrustumSPField, NeRFField):
    """Vanilla NeRF's field with SP through frustum offsets."""


class SPNeRFModel(SPModel, NeRFModel):
    config: SPNeRFModelConfig

    def populate_modules(self) -> None:
        with host_builds("nerfstudio.models.vanilla_nerf", SPPositionNeRFField):
            super().populate_modules()

    def attach_sp(self) -> None:
        self.field_coarse.use_preconditioner(self.sp)
        self.field_fine.use_preconditioner(self.sp)


def _check_box_boundary(sp: SPConfig, bounded: bool, method: str) -> None:
    """A bounded field zeroes density outside its box: SP should reflect there, and must not
    reflect in a contracted (unbounded) scene. A mismatch is the user's flag: :class:`InputError`,
    one line under ``ns-train``."""
    if not sp.enabled:
        return
    if bounded and sp.boundary == "none":
        log.warning(
            "%s: the field is bounded by the scene box but --pipeline.model.sp.boundary is 'none': perturbed samples "
            "near the box fall into the zeroed outside; pass --pipeline.model.sp.boundary reflect",
            method,
        )
    if not bounded and sp.boundary != "none":
        raise InputError(
            f"{method}: --pipeline.model.sp.boundary {sp.boundary} needs a bounded scene, but scene contraction is on; "
            "pass --pipeline.model.sp.boundary none (or --pipeline.model.disable-scene-contraction True)"
        )


@dataclass
class SPNerfactoModelConfig(SPModelConfig, NerfactoModelConfig):
    """Nerfacto with SP on the main field's sample positions (world space, before contraction)."""

    _target: Type = field(default_factory=lambda: SPNerfactoModel)
    sp: SPConfig = field(default_factory=lambda: dataclasses.replace(POSITION_FIELD_SP))


class SPNerfactoField(FrustumSPField, NerfactoField):
    """Nerfacto's main field with SP through frustum offsets (the proposal networks stay plain)."""


class SPNerfactoModel(SPModel, NerfactoModel):
    config: SPNerfactoModelConfig

    def populate_modules(self) -> None:
        _check_box_boundary(self.config.sp, self.config.disable_scene_contraction, "sp-nerfacto")
        from sp_plugins.nerfstudio import hash_encoding

        # Where tcnn cannot run: nerfstudio's torch modules (no slow-path warnings), then our hash grids
        device = self.kwargs.get("device")
        ours = hash_encoding.use_sp_hash_grids(device)
        if ours:
            self.config = dataclasses.replace(self.config, implementation="torch")
        with host_builds("nerfstudio.models.nerfacto", SPNerfactoField):
            super().populate_modules()
        if ours:
            hash_encoding.setup_host_modules(self, "sp-nerfacto", device)

    def attach_sp(self) -> None:
        self.field.use_preconditioner(self.sp)


@dataclass
class SPTensoRFModelConfig(SPModelConfig, TensoRFModelConfig):
    """TensoRF with SP on the fine field's sample positions, reflected inside the scene box."""

    _target: Type = field(default_factory=lambda: SPTensoRFModel)
    sp: SPConfig = field(default_factory=lambda: dataclasses.replace(POSITION_FIELD_SP, boundary="reflect"))


class SPTensoRFField(FrustumSPField, TensoRFField):
    """TensoRF's field with SP through frustum offsets."""


class SPTensoRFModel(SPModel, TensoRFModel):
    config: SPTensoRFModelConfig

    def populate_modules(self) -> None:
        _check_box_boundary(self.config.sp, True, "sp-tensorf")
        if self.config.sp.alpha_grid:
            # nerfstudio 1.1.5's TensorVMEncoding detaches its sample coordinates
            raise InputError(
                "--pipeline.model.sp.alpha-grid True cannot learn on sp-tensorf: nerfstudio's TensoRF encoding detaches "
                "its sample positions, so no gradient reaches the alpha grid; use a global alpha (the default)"
            )
        with host_builds("nerfstudio.models.tensorf", SPTensoRFField):
            super().populate_modules()

    def attach_sp(self) -> None:
        self.field.use_preconditioner(self.sp)
