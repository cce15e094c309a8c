"""sdfstudio's models build torchmetrics' LPIPS, which downloads AlexNet weights: offline it fails.

Targets sdfstudio commit 370902a: ``SurfaceModel.populate_modules`` (and the NeRF models) call
``LearnedPerceptualImagePatchSimilarity()``, bound by name at module import. After those modules
execute, the name is replaced by a factory that builds the real metric when the backbone weights
are in torch hub's cache and otherwise returns :class:`MissingLPIPS` (NaN, one log line), never
downloading. Either way the metric is held outside the module tree, so it is never in a
checkpoint: a checkpoint trained offline loads where the weights are cached and vice versa
(sdfstudio loads checkpoints strictly).
"""

from __future__ import annotations

import logging
import os
from typing import Any, Optional

import torch

from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT, after_exec

__all__ = ["HOST_COMMIT", "MissingLPIPS", "install", "lpips_weights_path"]

log = logging.getLogger(__name__)

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


def lpips_weights_path() -> Optional[str]:
    """Where torch hub caches the AlexNet backbone of torchmetrics' default LPIPS."""
    try:
        from torchvision.models import AlexNet_Weights
    except ImportError:
        return None
    return os.path.join(torch.hub.get_dir(), "checkpoints", os.path.basename(AlexNet_Weights.DEFAULT.url))


class MissingLPIPS:
    """Stands in for LPIPS when its weights are not cached: NaN, no state."""

    available = False

    def __call__(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        return torch.tensor(float("nan"))

    def to(self, *args: Any, **kwargs: Any) -> "MissingLPIPS":
        return self


class OutsideStateDict:
    """The real metric, kept out of the model's module tree; follows its inputs' device."""

    available = True

    def __init__(self, metric: torch.nn.Module) -> None:
        self.metric = metric

    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        if self.metric.device != a.device:
            self.metric = self.metric.to(a.device)
        return self.metric(a, b)

    def to(self, *args: Any, **kwargs: Any) -> "OutsideStateDict":
        return self


_warned = False


def _offline_factory(real_cls):
    def build(*args: Any, **kwargs: Any):
        global _warned
        path = lpips_weights_path()
        net_type = kwargs.get("net_type", args[0] if args else "alex")
        if net_type == "alex" and path is not None and os.path.isfile(path):
            return OutsideStateDict(real_cls(*args, **kwargs))
        if not _warned:
            _warned = True
            log.warning("LPIPS skipped (NaN): its AlexNet weights are not in the torch hub cache (%s); "
                        "sp-plugins never downloads at run time", path)
        return MissingLPIPS()

    build.real = real_cls  # type: ignore[attr-defined]
    return build


def _patch(module) -> None:
    real = getattr(module, NAME, None)
    if real is not None and not hasattr(real, "real"):
        setattr(module, NAME, _offline_factory(real))


def install() -> None:
    for name in MODULES:
        after_exec(name, _patch)
