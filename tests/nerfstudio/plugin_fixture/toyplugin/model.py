"""A small NeRF: uniform samples, an MLP field that reads ``get_positions()``, RGB rendering.

With ``TOY_FIELD_LOG`` set, every field query appends one JSON line: whether the field was in
training mode and the largest distance between the positions it read and the plain sample
positions of the samples the *model* made (``field.reference``, set by the model before each call):
measured inside the field against the model's plain rays, so it sees any move, however made.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Dict, List, Type

import torch
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.base_field import Field
from nerfstudio.model_components.losses import MSELoss
from nerfstudio.model_components.ray_samplers import UniformSampler
from nerfstudio.model_components.renderers import RGBRenderer
from nerfstudio.models.base_model import Model, ModelConfig
from torch import nn


class ToyField(Field):
    def __init__(self, width: int = 16) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(3, width), nn.ReLU(), nn.Linear(width, 4))

    reference = None
    """The samples the model made (plain), set by the model before it calls the field."""

    def log_offset(self, read, plain) -> None:
        log = os.environ.get("TOY_FIELD_LOG")
        if log:
            with open(log, "a") as out:
                out.write(json.dumps({"training": self.training, "offset": float((read - plain).abs().max())}) + "\n")

    def get_density(self, ray_samples):
        x = ray_samples.frustums.get_positions()
        self.log_offset(x, self.reference.frustums.get_positions())
        h = self.mlp(x)
        return torch.nn.functional.softplus(h[..., :1]), h[..., 1:]

    def get_outputs(self, ray_samples, density_embedding=None):
        return {FieldHeadNames.RGB: torch.sigmoid(density_embedding)}


@dataclass
class ToyModelConfig(ModelConfig):
    _target: Type = field(default_factory=lambda: ToyModel)
    num_samples: int = 16
    """Samples per ray."""
    width: int = 16
    """Hidden width of the field's MLP."""


class ToyModel(Model):
    config: ToyModelConfig
    field_class: Type[ToyField] = ToyField
    """The field the model builds (a subclass's own field: set this)."""

    def populate_modules(self) -> None:
        super().populate_modules()
        self.field = self.field_class(self.config.width)
        self.sampler = UniformSampler(num_samples=self.config.num_samples)
        self.renderer = RGBRenderer(background_color="white")
        self.rgb_loss = MSELoss()

    def get_param_groups(self) -> Dict[str, List[nn.Parameter]]:
        return {"fields": list(self.field.parameters())}

    def get_outputs(self, ray_bundle):
        samples = self.sampler(ray_bundle)
        self.field.reference = samples
        out = self._last = self.field(samples)
        weights = samples.get_weights(out[FieldHeadNames.DENSITY])
        return {"rgb": self.renderer(rgb=out[FieldHeadNames.RGB], weights=weights)}

    def get_loss_dict(self, outputs, batch, metrics_dict=None):
        return {"rgb_loss": self.rgb_loss(batch["image"].to(outputs["rgb"].device)[..., :3], outputs["rgb"])}

    def get_image_metrics_and_images(self, outputs, batch):
        image = batch["image"].to(outputs["rgb"].device)[..., :3]
        psnr = -10 * torch.log10(((outputs["rgb"] - image) ** 2).mean())
        return {"psnr": float(psnr)}, {"img": outputs["rgb"]}
