"""MipNeRF's field with the SP offset added to the mean of each conical frustum's Gaussian.

MipNeRF encodes a Gaussian (mean, covariance) per sample with the integrated positional encoding.
SP moves the mean, ``mu + alpha * eps``, and keeps the covariance, so the integrated encoding
still low-passes the frequencies the frustum's footprint cannot resolve. ``Frustums.offsets``
cannot carry this: nerfstudio's ``get_gaussian_blob`` raises ``NotImplementedError`` when offsets
are set, hence a field subclass, which the host model builds itself (see
``sp_plugins.patches.nerfstudio_host_fields``).
"""

from __future__ import annotations

from typing import Dict, Tuple

from nerfstudio.cameras.rays import RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.vanilla_nerf_field import NeRFField
from nerfstudio.utils.math import Gaussians
from torch import Tensor

from sp_plugins.adapter.field import SPFieldMixin
from sp_plugins.core import StochasticPreconditioner
from sp_plugins.nerfstudio.frustum_sp import set_perturbed_offsets


class SPNeRFField(SPFieldMixin, NeRFField):
    """``NeRFField`` whose sample positions (or Gaussian means) are perturbed while SP is active.

    The host's ``MipNerfModel`` builds it with its own arguments, so every architecture setting is
    the host's."""

    def perturbed_gaussians(self, ray_samples: RaySamples, sp: StochasticPreconditioner) -> Gaussians:
        """The frustums' Gaussians with SP-perturbed means (the covariance is unchanged)."""
        blobs = ray_samples.frustums.get_gaussian_blob()
        mean = sp(blobs.mean.reshape(-1, 3)).view(blobs.mean.shape)
        return Gaussians(mean=mean, cov=blobs.cov)

    def forward(self, ray_samples: RaySamples, compute_normals: bool = False) -> Dict[FieldHeadNames, Tensor]:
        """The host's forward, averaged over ``sp.num_samples`` perturbations while SP is active."""
        plain = super().forward
        return self.over_draws(lambda: plain(ray_samples, compute_normals=compute_normals))

    def get_density(self, ray_samples: RaySamples) -> Tuple[Tensor, Tensor]:
        sp = self.sp
        if sp is None or not self.sp_active():
            return super().get_density(ray_samples)
        if not self.use_integrated_encoding:  # plain positions: the frustum-offset route
            previous = set_perturbed_offsets(ray_samples, sp)
            try:
                return super().get_density(ray_samples)
            finally:
                ray_samples.frustums.offsets = previous
        blobs = self.perturbed_gaussians(ray_samples, sp)
        if self.spatial_distortion is not None:
            blobs = self.spatial_distortion(blobs)
        hidden = self.mlp_base(self.position_encoding(blobs.mean, covs=blobs.cov))
        return self.field_output_density(hidden), hidden
