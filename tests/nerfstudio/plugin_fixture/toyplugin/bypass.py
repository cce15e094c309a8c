"""A plugin method whose field reads its positions from the samples' metadata, not from the frustums:
no seam can move them, so SP must refuse it instead of training without SP."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

import torch

from toyplugin.model import ToyField, ToyModel, ToyModelConfig


class BypassField(ToyField):
    def get_density(self, ray_samples):
        h = self.mlp(ray_samples.metadata["positions"])
        return torch.nn.functional.softplus(h[..., :1]), h[..., 1:]

    def get_outputs(self, ray_samples, density_embedding=None):
        return super().get_outputs(ray_samples, density_embedding)


class BypassModel(ToyModel):
    field_class = BypassField

    def get_outputs(self, ray_bundle):
        samples = self.sampler(ray_bundle)
        samples.metadata = {"positions": samples.frustums.get_positions().detach()}
        self.field.reference = samples
        out = self.field(samples)
        from nerfstudio.field_components.field_heads import FieldHeadNames

        weights = samples.get_weights(out[FieldHeadNames.DENSITY])
        return {"rgb": self.renderer(rgb=out[FieldHeadNames.RGB], weights=weights)}


@dataclass
class BypassModelConfig(ToyModelConfig):
    _target: Type = field(default_factory=lambda: BypassModel)
