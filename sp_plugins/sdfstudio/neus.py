"""SP variants of sdfstudio's NeuS family: neus, neus-facto, neuralangelo, bakedangelo.

Each model is the host model with :class:`~sp_plugins.sdfstudio.model.SPModel` in front and an
:class:`~sp_plugins.sdfstudio.sdf_field.SPSDFField`; ``sp.enabled=False`` is the host baseline.
Nothing else of the host's training changes (losses, samplers, NeuS cosine annealing, learning
rates), except in the Neuralangelo pair, where SP *replaces* coarse-to-fine:

- ``enable_progressive_hash_encoding=False``: all hash levels from step 0;
- ``enable_numerical_gradients_schedule=False``: the finite-difference step is fixed at the value
  sdfstudio's schedule ends on (``sdf_field.fd_step``: neuralangelo ``2 / max_res``, bakedangelo
  ``1 / max_res``, in contracted units);
- the curvature-loss weight schedule (a loss weight, not a representation schedule) is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.models.bakedangelo import BakedAngeloModel, BakedAngeloModelConfig
from nerfstudio.models.neuralangelo import NeuralangeloModel, NeuralangeloModelConfig
from nerfstudio.models.neus import NeuSModel, NeuSModelConfig
from nerfstudio.models.neus_facto import NeuSFactoModel, NeuSFactoModelConfig

from sp_plugins.sdfstudio.model import SPModel, SPModelConfig
from sp_plugins.sdfstudio.sdf_field import SPSDFField, SPSDFFieldConfig


class _AttachToField:
    field: SPSDFField

    def attach_sp(self) -> None:
        self.field.use_preconditioner(self.sp)  # type: ignore[attr-defined]


@dataclass
class SPNeuSModelConfig(SPModelConfig, NeuSModelConfig):
    """sdfstudio's NeuS with SP at the SDF field's queries."""

    _target: Type = field(default_factory=lambda: SPNeuSModel)
    sdf_field: SPSDFFieldConfig = field(default_factory=SPSDFFieldConfig)


class SPNeuSModel(_AttachToField, SPModel, NeuSModel):
    config: SPNeuSModelConfig


@dataclass
class SPNeuSFactoModelConfig(SPModelConfig, NeuSFactoModelConfig):
    """sdfstudio's neus-facto (proposal sampler, hash grid) with SP at the SDF field's queries."""

    _target: Type = field(default_factory=lambda: SPNeuSFactoModel)
    sdf_field: SPSDFFieldConfig = field(default_factory=SPSDFFieldConfig)


class SPNeuSFactoModel(_AttachToField, SPModel, NeuSFactoModel):
    config: SPNeuSFactoModelConfig


@dataclass
class SPNeuralangeloModelConfig(SPModelConfig, NeuralangeloModelConfig):
    """sdfstudio's Neuralangelo with SP in place of its coarse-to-fine."""

    _target: Type = field(default_factory=lambda: SPNeuralangeloModel)
    sdf_field: SPSDFFieldConfig = field(default_factory=SPSDFFieldConfig)
    enable_progressive_hash_encoding: bool = False
    enable_numerical_gradients_schedule: bool = False


class SPNeuralangeloModel(_AttachToField, SPModel, NeuralangeloModel):
    config: SPNeuralangeloModelConfig


@dataclass
class SPBakedAngeloModelConfig(SPModelConfig, BakedAngeloModelConfig):
    """sdfstudio's bakedangelo (Neuralangelo on BakedSDF) with SP in place of its coarse-to-fine."""

    _target: Type = field(default_factory=lambda: SPBakedAngeloModel)
    sdf_field: SPSDFFieldConfig = field(default_factory=SPSDFFieldConfig)
    enable_progressive_hash_encoding: bool = False
    enable_numerical_gradients_schedule: bool = False


class SPBakedAngeloModel(_AttachToField, SPModel, BakedAngeloModel):
    config: SPBakedAngeloModelConfig


__all__ = [
    "SPBakedAngeloModel",
    "SPBakedAngeloModelConfig",
    "SPNeuSFactoModel",
    "SPNeuSFactoModelConfig",
    "SPNeuSModel",
    "SPNeuSModelConfig",
    "SPNeuralangeloModel",
    "SPNeuralangeloModelConfig",
]
