"""A plugin SDF method: the field reads ``get_start_positions()`` and takes its eikonal gradient there."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

import torch
from nerfstudio.field_components.field_heads import FieldHeadNames

from toyplugin.model import ToyField, ToyModel, ToyModelConfig


class ToySDFField(ToyField):
    """SDF from an MLP at the frustum starts; density by VolSDF's Laplace CDF; eikonal gradient by autograd."""

    def forward(self, ray_samples, compute_normals=False):
        x = ray_samples.frustums.get_start_positions()
        self.log_offset(x, self.reference.frustums.get_start_positions())
        with torch.enable_grad():
            if not x.requires_grad:
                x = x.requires_grad_(True)
            h = self.mlp(x)
            sdf = h[..., :1]
            (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=self.training)
        beta = 0.1
        density = (0.5 + 0.5 * torch.sign(sdf) * torch.expm1(-sdf.abs() / beta)) / beta
        return {FieldHeadNames.DENSITY: density.clamp_min(0), FieldHeadNames.RGB: torch.sigmoid(h[..., 1:]),
                FieldHeadNames.GRADIENT: grad}


class ToySDFModel(ToyModel):
    field_class = ToySDFField

    def get_outputs(self, ray_bundle):
        outputs = super().get_outputs(ray_bundle)
        if self.training:  # a scalar: evaluation concatenates per-chunk outputs
            outputs["eikonal"] = ((self._last[FieldHeadNames.GRADIENT].norm(dim=-1) - 1) ** 2).mean()
        return outputs

    def get_loss_dict(self, outputs, batch, metrics_dict=None):
        losses = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training:
            losses["eikonal_loss"] = 0.1 * outputs["eikonal"]
        return losses


@dataclass
class ToySDFModelConfig(ToyModelConfig):
    _target: Type = field(default_factory=lambda: ToySDFModel)
