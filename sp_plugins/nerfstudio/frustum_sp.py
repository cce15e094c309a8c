"""SP for any nerfstudio field that reads ``ray_samples.frustums.get_positions()``.

nerfstudio's ``Frustums`` carry an optional ``offsets`` tensor that ``get_positions()`` adds to
every sample position (the hook its D-NeRF temporal distortion uses). While training and alpha > 0,
the field's ``forward`` sets ``offsets`` so that ``get_positions()`` returns the perturbed position
``sp(x)`` (reflected into the scene box when the SP boundary is ``reflect``, so that a bounded
field's samples do not land in its zeroed outside), and restores the previous offsets afterwards, so samplers, renderers and losses that read the same ``RaySamples`` later see
the unperturbed positions. Density and colour read the same offsets, so they see one blurred field.

The fields are host subclasses (:class:`FrustumSPField` first among the bases) that the host
model builds itself with its own arguments.

The proposal networks of nerfacto and the coarse-to-fine PDF samplers are samplers: they place
samples and are not perturbed (as for the NeuS sampler's SDF queries).

Gaussian-blob fields (MipNeRF) cannot use ``offsets`` (``get_gaussian_blob`` refuses them): see
:mod:`sp_plugins.nerfstudio.mipnerf`.
"""

from __future__ import annotations

from typing import Any, Optional

import torch
from nerfstudio.cameras.rays import RaySamples

from sp_plugins.adapter.field import SPFieldMixin
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


class FrustumSPField(SPFieldMixin):
    """Mixin for a host field that reads ``get_positions()``: list it first among the bases.

    While training and ``sp`` is active, ``forward`` sets the frustum offsets to the perturbation
    (averaged over ``sp.num_samples`` draws) and restores them afterwards. The host model builds
    the subclass with its own arguments (``sp_plugins.patches.nerfstudio_host_fields``), so
    modules and checkpoints are the host's. Calls without a ``RaySamples`` (``density_fn``
    queries of proposal samplers) stay plain."""

    __sp_variant__ = True

    def forward(self, *args: Any, **kwargs: Any):
        plain = super().forward  # type: ignore[misc]
        samples = _ray_samples(args, kwargs)
        if samples is None or not self.sp_active():
            return plain(*args, **kwargs)
        sp = self.sp
        assert sp is not None

        def one_draw():
            previous = set_perturbed_offsets(samples, sp)
            try:
                return plain(*args, **kwargs)
            finally:
                samples.frustums.offsets = previous

        return self.perturbed(one_draw)
