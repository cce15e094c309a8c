"""Our nerfstudio SDF field: ``SDFField`` with masked hash-grid levels and numerical gradients.

Neuralangelo-lite needs what nerfstudio's ``SDFField`` lacks: hash levels that coarse-to-fine can
switch on one by one, and normals from a finite-difference stencil whose step follows the finest
active level. That is this field's reason to exist; it does not perturb anything itself. SP enters
through the one seam (:mod:`sp_plugins.nerfstudio.seam`), which hands ``get_outputs`` samples whose
start positions are moved: the SDF, geometry feature, colour and the autograd gradient are taken at
the moved point ``q``, and the stencil is evaluated around ``q``, so all its points share one offset.

The NeuS sampler's ``get_sdf`` (no-grad importance sampling) sees the plain field by default: it
only places samples, one perturbed draw would jitter the placement without blurring it in
expectation, and the plain field costs nothing extra. ``perturb_sampler_queries`` moves its samples
too, as the seam would.

The hash grid is :class:`sp_plugins.encodings.HashGrid` (tiny-cuda-nn when it runs, torch
otherwise); without ``use_grid_feature`` there is no grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Literal, Optional, Tuple, Type

import torch
import torch.nn.functional as F
from jaxtyping import Float
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.sdf_field import SDFField, SDFFieldConfig
from torch import Tensor, nn

from sp_plugins.adapter import hosts
from sp_plugins.adapter.field import SPFieldMixin
from sp_plugins.core import finite_differences
from sp_plugins.adapter.errors import InputError
from sp_plugins.encodings import HashGrid
from sp_plugins.nerfstudio import seam
from sp_plugins.patches import registry
from sp_plugins.patches.nerfstudio_marching_cubes import serving_mesher

LAPLACIAN = "sdf_laplacian"
"""Key of the stencil Laplacian in the field outputs (numerical gradients, training only)."""

GRID_SPAN = 4.0
"""``SDFField`` maps contracted positions in [-2, 2] onto the grid's [0, 1]: one grid unit is 4
scene units (inside the unit box, where the contraction is the identity)."""


@dataclass
class CoarseToFineSDFFieldConfig(SDFFieldConfig):
    """``SDFFieldConfig`` plus numerical gradients and the SP sampler switch."""

    _target: Type = field(default_factory=lambda: CoarseToFineSDFField)
    inside_outside: bool = False
    """Objects seen from outside (the SDF is negative inside); True for indoor rooms."""
    numerical_gradients: bool = False
    """Normals from a finite-difference stencil (Neuralangelo) instead of autograd."""
    stencil: Literal["6pt", "4pt"] = "6pt"
    """6pt: central differences (Neuralangelo); 4pt: tetrahedron, cheaper."""
    fd_step: Optional[float] = None
    """Finite-difference step in scene units; None: the cell size of the finest active level."""
    perturb_sampler_queries: bool = False
    """Let the NeuS sampler's SDF queries see the perturbed field too."""


class _NoGrid(nn.Module):
    """Zero-width stand-in when the field uses no grid feature (plain NeuS)."""

    n_output_dims = 0

    def forward(self, x: Tensor) -> Tensor:
        return x.new_zeros(*x.shape[:-1], 0)


class CoarseToFineSDFField(SPFieldMixin, SDFField):
    """``SDFField`` with masked levels and numerical gradients; the seam moves its samples."""

    config: CoarseToFineSDFFieldConfig

    def __init__(self, config: CoarseToFineSDFFieldConfig, aabb, num_images: int, use_average_appearance_embedding: bool = False, spatial_distortion=None) -> None:
        if config.encoding_type != "hash":
            raise InputError(
                f"--pipeline.model.sdf-field.encoding-type {config.encoding_type}: our SDF methods support 'hash' "
                "(with --pipeline.model.sdf-field.use-grid-feature True or False)"
            )
        if config.numerical_gradients and not config.use_grid_feature:
            raise InputError(
                "--pipeline.model.sdf-field.numerical-gradients True needs --pipeline.model.sdf-field.use-grid-feature True "
                "(the finite-difference step follows the grid levels)"
            )
        in_dim = 3 + 36 + (config.num_levels * config.features_per_level if config.use_grid_feature else 0)
        if config.num_layers == 3 or (config.num_layers >= 4 and config.hidden_dim <= in_dim):
            raise InputError(
                f"--pipeline.model.sdf-field.num-layers {config.num_layers} with --pipeline.model.sdf-field.hidden-dim "
                f"{config.hidden_dim}: the SDF MLP re-injects its {in_dim}-wide input after layer 4, so use num-layers <= 2, "
                f"or num-layers >= 4 with hidden-dim > {in_dim}"
            )
        with registry.scope("nerfstudio_sdf_field"):  # tcnn's stand-in for this construction only
            super().__init__(config, aabb, num_images, use_average_appearance_embedding, spatial_distortion)
        n_levels = config.num_levels if config.use_grid_feature else 0
        # Coarse-to-fine state lives in buffers so a checkpoint restores it (eval, export, resume).
        self.register_buffer("active_levels", torch.tensor(n_levels, dtype=torch.long))
        self.register_buffer("fd_step", torch.tensor(self.level_cell_size(n_levels - 1) if n_levels else 0.0))
        self._fd_step = float(self.fd_step)  # Python mirror: reading the buffer per step would sync a GPU
        if config.fd_step is not None:
            self.set_fd_step(config.fd_step)

    def initialize_geo_layers(self) -> None:
        """Swap in our encoding before the MLP is sized on it."""
        if not self.config.use_grid_feature:
            self.encoding = _NoGrid()
        elif not isinstance(self.encoding, HashGrid):  # a real tcnn.Encoding: wrap it so levels can be masked
            self.encoding = HashGrid(
                num_levels=self.config.num_levels,
                features_per_level=self.config.features_per_level,
                log2_hashmap_size=self.config.log2_hashmap_size,
                base_resolution=self.config.base_res,
                max_resolution=self.config.max_res,
                interpolation="Smoothstep" if self.config.smoothstep else "Linear",
                grid_type="Hash" if self.config.use_hash else "Dense",
                backend="auto",
            )
        super().initialize_geo_layers()

    # -- coarse-to-fine controls -----------------------------------------------------------------
    def level_cell_size(self, level: int) -> float:
        """Cell size of grid level ``level`` in scene units (for the finite-difference step)."""
        scale = self.encoding.levels[max(level, 0)].scale
        return GRID_SPAN / scale

    def set_active_levels(self, n: int) -> None:
        """Coarse-to-fine: only the ``n`` coarsest grid levels contribute."""
        self.active_levels.fill_(int(n))
        self.encoding.set_active_levels(int(n))

    def set_fd_step(self, step: float) -> None:
        self._fd_step = float(step)
        self.fd_step.fill_(self._fd_step)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self._fd_step = float(self.fd_step)
        if self.config.use_grid_feature:
            self.encoding.set_active_levels(int(self.active_levels))

    # -- queries ---------------------------------------------------------------------------------
    def sp_read_positions(self, frustums: Frustums) -> Float[Tensor, "*bs 3"]:
        """Where this field queries: the bins' starts (a :class:`~sp_plugins.adapter.field.ReadPointField`,
        declared as any field of a user's would be)."""
        return frustums.get_start_positions()

    def forward_geonetwork(self, inputs: Tensor) -> Tensor:
        serving_mesher(self)  # ns-export's mesher asks whether a callable evaluates our field
        return super().forward_geonetwork(inputs)

    def sdf_of(self, x: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        return self.forward_geonetwork(x)[:, 0]

    def geometry(
        self, x: Float[Tensor, "n 3"]
    ) -> Tuple[Float[Tensor, "n 1"], Float[Tensor, "n geo"], Float[Tensor, "n 3"], Optional[Tensor]]:
        """``(sdf, geo_feature, gradient, laplacian)`` at ``x`` (the seam's moved points in training)."""
        if self.config.numerical_gradients:
            hidden = self.forward_geonetwork(x)
            sdf, geo = torch.split(hidden, [1, self.config.geo_feat_dim], dim=-1)
            grad, lap = finite_differences(
                self.sdf_of, x, self._fd_step, self.config.stencil, centre_values=sdf[:, 0] if self.training else None
            )
            return sdf, geo, grad, lap
        with torch.enable_grad():
            if not x.requires_grad:
                x = x.requires_grad_(True)
            hidden = self.forward_geonetwork(x)
            sdf, geo = torch.split(hidden, [1, self.config.geo_feat_dim], dim=-1)
            (grad,) = torch.autograd.grad(sdf, x, torch.ones_like(sdf), create_graph=self.training, retain_graph=True)
        return sdf, geo, grad, None

    def get_sdf(self, ray_samples: RaySamples) -> Float[Tensor, "num_samples ... 1"]:
        if self.config.perturb_sampler_queries and self.sp_active():
            ray_samples = seam.perturbed_samples(ray_samples, self.sp, self.sp_read_positions)  # type: ignore[arg-type]
        x = ray_samples.frustums.get_start_positions().reshape(-1, 3)
        hidden = self.forward_geonetwork(x).view(*ray_samples.frustums.shape, -1)
        return hidden[..., :1]

    def get_outputs(
        self, ray_samples: RaySamples, density_embedding: Optional[Tensor] = None, return_alphas: bool = False
    ) -> Dict[FieldHeadNames, Tensor]:
        if ray_samples.camera_indices is None:
            raise AttributeError("Camera indices are not provided.")
        shape = ray_samples.frustums.directions.shape[:-1]
        x = ray_samples.frustums.get_start_positions().reshape(-1, 3)
        directions = ray_samples.frustums.directions.reshape(-1, 3)
        sdf, geo, grad, lap = self.geometry(x)
        rgb = self.get_colors(x, directions, grad, geo, ray_samples.camera_indices.squeeze())
        sdf = sdf.view(*shape, 1)
        grad = grad.view(*shape, 3)
        outputs: Dict = {
            FieldHeadNames.RGB: rgb.view(*shape, 3),
            FieldHeadNames.SDF: sdf,
            FieldHeadNames.NORMALS: F.normalize(grad, p=2, dim=-1),
            FieldHeadNames.GRADIENT: grad,
        }
        if lap is not None:
            outputs[LAPLACIAN] = lap.view(*shape, 1)
        if return_alphas:
            outputs[FieldHeadNames.ALPHA] = self.get_alpha(ray_samples, sdf, grad)
        return outputs


def __getattr__(name: str):
    """Names renamed since a run folder was saved (the nerfstudio host's ``renamed`` table)."""
    return hosts.renamed_attribute(__name__, name)
