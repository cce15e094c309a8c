"""A plugin MipNeRF-style method: the field encodes each frustum's Gaussian blob (mean and covariance)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

import torch

from toyplugin.model import ToyField, ToyModel, ToyModelConfig


class ToyBlobField(ToyField):
    def get_density(self, ray_samples):
        blob = ray_samples.frustums.get_gaussian_blob()
        self.log_offset(blob.mean, self.reference.frustums.get_gaussian_blob().mean)
        h = self.mlp(blob.mean) * torch.exp(-blob.cov.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True))
        return torch.nn.functional.softplus(h[..., :1]), h[..., 1:]


class ToyBlobModel(ToyModel):
    field_class = ToyBlobField


@dataclass
class ToyBlobModelConfig(ToyModelConfig):
    _target: Type = field(default_factory=lambda: ToyBlobModel)
