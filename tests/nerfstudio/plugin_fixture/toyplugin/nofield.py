"""A plugin method that renders without any field queried with samples (a learned colour per
image, like a method that rasterises): SP has nothing to perturb and must refuse it in one line."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

import torch
from torch import nn

from toyplugin.model import ToyModel, ToyModelConfig


class NoFieldModel(ToyModel):
    def populate_modules(self) -> None:
        super().populate_modules()
        del self.field
        self.colour = nn.Parameter(torch.full((3,), 0.5))

    def get_param_groups(self):
        return {"fields": [self.colour]}

    def get_outputs(self, ray_bundle):
        return {"rgb": self.colour.expand(*ray_bundle.origins.shape[:-1], 3)}


@dataclass
class NoFieldModelConfig(ToyModelConfig):
    _target: Type = field(default_factory=lambda: NoFieldModel)
