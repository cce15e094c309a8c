"""SP for any nerfstudio field that reads ``ray_samples.frustums.get_positions()``.

nerfstudio's ``Frustums`` carry an optional ``offsets`` tensor that ``get_positions()`` adds to
every sample position (the hook its D-NeRF temporal distortion uses). While training and alpha > 0,
the field's forward sets ``offsets`` so that ``get_positions()`` returns the perturbed position
``sp(x)`` (reflected into the scene box when the SP boundary is ``reflect``, so that a bounded
field's samples do not land in its zeroed outside), and restores the previous offsets afterwards, so samplers, renderers and losses that read the same ``RaySamples`` later see
the unperturbed positions. Density and colour read the same offsets, so they see one blurred field.

The proposal networks of nerfacto and the coarse-to-fine PDF samplers are samplers: they place
samples and are not perturbed (as for the NeuS sampler's SDF queries).

Gaussian-blob fields (MipNeRF) cannot use ``offsets`` (``get_gaussian_blob`` refuses them): see
:mod:`sp_plugins.nerfstudio.mipnerf`.
"""

from __future__ import annotations

from typing import Any, Optional

import torch
from nerfstudio.cameras.rays import RaySamples
from torch import nn

from sp_plugins.core import StochasticPreconditioner


def _ray_samples(args: tuple, kwargs: dict) -> Optional[RaySamples]:
    candidate = kwargs.get("ray_samples", args[0] if args else None)
    return candidate if isinstance(candidate, RaySamples) else None


def set_perturbed_offsets(ray_samples: RaySamples, sp: StochasticPreconditioner) -> Optional[torch.Tensor]:
    """Set ``ray_samples.frustums.offsets`` so that ``get_positions()`` is ``sp(positions)``.

    Returns the offsets that were there before (to restore). Existing offsets are kept: the
    perturbation applies to the already-offset position."""
    frustums = ray_samples.frustums
    previous = frustums.offsets
    if not sp.active:
        return previous
    x = frustums.get_positions()
    shape = x.shape
    q = sp(x.reshape(-1, 3)).view(shape)
    base = previous if previous is not None else 0.0
    frustums.offsets = base + (q - x)  # get_positions() = x + (q - x) = q, gradients included
    return previous


def attach_frustum_sp(field: nn.Module, sp: StochasticPreconditioner) -> None:
    """Perturb the positions ``field`` reads (via frustum offsets) while ``sp`` is active.

    nerfstudio's models call ``field.forward(...)`` directly, which bypasses module hooks, so the
    instance's ``forward`` is wrapped (not saved in checkpoints; :func:`detach_frustum_sp` undoes it).
    """
    if "forward" in field.__dict__:
        raise ValueError(f"{type(field).__name__}: SP is already attached to this field (or its forward is wrapped)")
    plain = field.forward

    def forward(*args: Any, **kwargs: Any):
        samples = _ray_samples(args, kwargs)
        if samples is None or not (field.training and sp.active):
            return plain(*args, **kwargs)

        def one_draw():
            previous = set_perturbed_offsets(samples, sp)
            try:
                return plain(*args, **kwargs)
            finally:
                samples.frustums.offsets = previous

        return sp.mean_over_draws(one_draw)  # sp.num_samples draws, averaged

    field.forward = forward  # type: ignore[method-assign]


def detach_frustum_sp(field: nn.Module) -> None:
    """Undo :func:`attach_frustum_sp`."""
    field.__dict__.pop("forward", None)
