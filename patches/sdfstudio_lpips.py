"""sdfstudio's models build torchmetrics' LPIPS, which downloads AlexNet weights: offline it fails.

Targets sdfstudio commit 370902a: ``SurfaceModel.populate_modules`` (and the NeRF models) call
``LearnedPerceptualImagePatchSimilarity()``, bound by name at module import. After those modules
execute, the name is replaced by the factory of :mod:`sp_plugins.adapter.lpips`, which builds the
real metric when the backbone weights are in torch hub's cache and otherwise returns
:class:`MissingLPIPS` (NaN, one log line), never downloading. Either way the metric is held outside the module tree, so it is never in a
checkpoint: a checkpoint trained offline loads where the weights are cached and vice versa
(sdfstudio loads checkpoints strictly).
"""

from __future__ import annotations

from sp_plugins.adapter.lpips import MissingLPIPS, lpips_weights_path, offline_factory
from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT, after_exec

__all__ = ["HOST_COMMIT", "MissingLPIPS", "install", "lpips_weights_path"]

MODULES = (
    "nerfstudio.models.base_surface_model",
    "nerfstudio.models.nerfacto",
    "nerfstudio.models.mipnerf",
    "nerfstudio.models.vanilla_nerf",
    "nerfstudio.models.tensorf",
    "nerfstudio.models.instant_ngp",
    "nerfstudio.models.semantic_nerfw",
)
NAME = "LearnedPerceptualImagePatchSimilarity"


def _patch(module) -> None:
    real = getattr(module, NAME, None)
    if real is not None and not hasattr(real, "real"):
        setattr(module, NAME, offline_factory(real, detach=True))


def install() -> None:
    for name in MODULES:
        after_exec(name, _patch)
