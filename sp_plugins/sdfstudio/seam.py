"""The one seam of the sdfstudio adapter: the SDF field's scene contraction (sdfstudio 370902a).

Why here: sdfstudio's ``SDFField.get_outputs`` (the query that renders and that every loss reads)
maps its sample positions through the field's ``spatial_distortion`` before anything else, and
then does everything at the result: SDF, geometry feature, the autograd gradient *with respect to
that tensor*, the 6-point numerical stencil around it (``gradient(..., skip_spatial_distortion=True)``),
colour and ``points_norm``. So making that mapping ``sp(contraction(x))`` (:class:`PerturbedContraction`
inside :class:`SeamSDFField`) perturbs every sample once, takes the normal where the field was queried,
and gives all six stencil points one offset, for every sdfstudio SDF method, without copying or
wrapping sdfstudio's ``get_outputs``. The nerfstudio counterpart is
:mod:`sp_plugins.nerfstudio.seam` (moved ``RaySamples`` handed to every field a model calls with them):
nerfstudio's fields share no contraction, sdfstudio's SDF methods all share this field.

- The perturbation lives in the contracted frame, reflected into the contraction's range
  ``[-2, 2]^3`` (the hash grid's domain); inside the unit box the contraction is the identity,
  so ``alpha`` is in scene units there. It acts only while training with alpha > 0.
- ``get_sdf`` (NeuS up-sampling, under no_grad) and ``get_density`` (VolSDF's sampler) only place
  samples: they see the plain field by default, as in our nerfstudio adapter (one perturbed draw
  would jitter the placement without blurring it in expectation). ``perturb_sampler_queries``
  turns them on. Proposal networks (neus-facto, bakedangelo) are samplers too and are not
  perturbed.
- Evaluation, rendering and mesh extraction (``forward_geonetwork`` called directly) always see
  the plain field.
- "Reached" means what it means in the nerfstudio adapter: a field query read positions SP moved.
  Here the SDF field queries exactly what its contraction returns, so the contraction records the
  largest move of the first positions it returned (a device scalar on the field's handle), and
  :func:`check_reached`, run by the model after the first training step with alpha > 0, reads it
  once and refuses a run that moved none.
- The hook for a field that is not called with ray samples (its positions come in as a tensor):
  the seam sits in a module every query passes (here the contraction, :class:`PerturbedContraction`),
  sharing the field's :class:`~sp_plugins.adapter.field.PreconditionerHandle`; it counts its moved
  calls and the first move on that handle, which is all :func:`check_reached` reads.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Optional, Type

import torch
from nerfstudio.cameras.rays import RaySamples
from nerfstudio.fields.sdf_field import SDFField, SDFFieldConfig
from torch import Tensor, nn

from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.field import PreconditionerHandle, SPFieldMixin
from sp_plugins.adapter import hosts
from sp_plugins.adapter import tables
from sp_plugins.sdfstudio import table
from sp_plugins.core import StochasticPreconditioner

CONTRACTED_BOUNDS = (-2.0, 2.0)
"""Range of sdfstudio's scene contraction, mapped onto the hash grid's [0, 1] by SDFField."""


@dataclass
class SeamSDFFieldConfig(SDFFieldConfig):
    """``SDFFieldConfig`` plus a fixed finite-difference step and the SP sampler switch."""

    _target: Type = field(default_factory=lambda: SeamSDFField)
    fd_step: Optional[float] = None
    """Numerical-gradient step in the contracted frame the SDF is queried in (scene units inside the
    contraction's unit ball, where it is the identity; the nerfstudio adapter's ``fd_step`` is in
    scene units everywhere), fixed for the whole run (SP runs, which drop Neuralangelo's shrinking
    schedule). None keeps sdfstudio's behaviour."""
    perturb_sampler_queries: bool = False
    """Let the NeuS up-sampler's ``get_sdf`` and VolSDF's ``get_density`` see the perturbed field."""


class PerturbedContraction(nn.Module):
    """``sp(inner(x))``: the field's spatial distortion followed by the perturbation.

    Holds no state of its own (``inner`` is sdfstudio's stateless ``SceneContraction``; the
    preconditioner is reached through the field's :class:`PreconditionerHandle`, a plain
    attribute), so the field's checkpoint keys are sdfstudio's."""

    def __init__(self, inner: Optional[nn.Module]) -> None:
        super().__init__()
        self.inner = inner
        self.sp_handle: Optional[PreconditionerHandle] = None

    def forward(self, x: Tensor) -> Tensor:
        plain = x if self.inner is None else self.inner(x)
        handle = self.sp_handle
        if handle is None or handle.sp is None or not handle.sp.active:
            return plain
        handle.perturbed_calls += 1
        moved = handle.sp(plain)
        if handle.first_move is None:  # once per run, device-side: check_reached reads it
            handle.first_move = (moved - plain).detach().abs().max()
        return moved


@functools.lru_cache(maxsize=None)
def read_point(cls: type) -> str:
    """The ``Frustums`` accessor a field of class ``cls`` queries at: ``table.READ_POINTS``' entry for it or its
    nearest base (looked up once per class), else ``get_positions``."""
    return tables.read_point(table.READ_POINTS, cls)


def check_reached(model: nn.Module, model_name: str, step: int) -> None:
    """After the first training step with alpha > 0: the queries of ``model``'s SDF field
    (``model.field``) went through the perturbed contraction and the positions really moved. Runs
    once per run; one device read (the first move), so a run whose perturbation is drawn but not
    applied stops at once instead of training a baseline under an SP name."""
    handle = getattr(getattr(model, "field", None), "sp_handle", None)
    calls = 0 if handle is None else handle.perturbed_calls
    if not calls:
        raise InputError(
            f"SP reached no SDF query of {model_name} in training step {step}: the field's scene contraction was not "
            "called while training with alpha > 0, so no position was perturbed; this is a bug of sp-plugins, please report it"
        )
    move = float(handle.first_move) if handle.first_move is not None else 0.0  # type: ignore[union-attr]
    if not move > 0:
        raise InputError(
            f"SP reached the SDF field of {model_name} in training step {step} but moved no position (largest move "
            f"{move:g}): the perturbation is not applied; this is a bug of sp-plugins, please report it"
        )


class SeamSDFField(SPFieldMixin, SDFField):
    """``SDFField`` whose training queries go through a :class:`StochasticPreconditioner`."""

    config: SeamSDFFieldConfig

    def __init__(self, config: SeamSDFFieldConfig, aabb, num_images: int, use_average_appearance_embedding: bool = False, spatial_distortion=None) -> None:
        super().__init__(config, aabb, num_images, use_average_appearance_embedding, spatial_distortion)
        self.spatial_distortion = PerturbedContraction(spatial_distortion)
        if config.fd_step is not None:
            self.set_numerical_gradients_delta(config.fd_step)

    # -- SP controls ----------------------------------------------------------------------------
    def use_preconditioner(self, sp: Optional[StochasticPreconditioner]) -> None:
        """Perturb queries through ``sp`` (owned and checkpointed by the model, not the field);
        the contraction shares the field's handle."""
        super().use_preconditioner(sp)
        self.spatial_distortion.sp_handle = self.sp_handle

    def perturb(self, x: Tensor) -> Tensor:
        return x if self.sp is None else self.sp(x)

    def set_numerical_gradients_delta(self, delta: float) -> None:
        """Host callbacks shrink the step; a fixed ``fd_step`` wins."""
        fixed = getattr(self.config, "fd_step", None)
        super().set_numerical_gradients_delta(delta if fixed is None else fixed)

    # -- sampler queries ---------------------------------------------------------------------------
    def _sampler_positions(self, ray_samples: RaySamples) -> Tensor:
        x = getattr(ray_samples.frustums, read_point(type(self)))().reshape(-1, 3)
        return self.perturb(x) if self.config.perturb_sampler_queries else x

    def get_sdf(self, ray_samples: RaySamples) -> Tensor:
        hidden = self.forward_geonetwork(self._sampler_positions(ray_samples))
        return hidden[:, :1].view(*ray_samples.frustums.shape, 1)

    def get_density(self, ray_samples: RaySamples):
        hidden = self.forward_geonetwork(self._sampler_positions(ray_samples)).view(*ray_samples.frustums.shape, -1)
        sdf, geo_feature = torch.split(hidden, [1, self.config.geo_feat_dim], dim=-1)
        return self.laplace_density(sdf), geo_feature


def __getattr__(name: str):
    """Names renamed since a run folder was saved (the sdfstudio host's ``renamed`` table)."""
    return hosts.renamed_attribute(__name__, name)
