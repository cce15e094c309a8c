"""LPIPS that never downloads, for both hosts: the real metric when its backbone weights are
cached, else a stand-in that returns NaN.

Every model of both hosts builds torchmetrics' LPIPS, whose constructor fetches an ImageNet
backbone from the network: offline (here, and on many clusters) it fails. :func:`offline_factory`
wraps the metric class: it builds the real metric when torch hub's cache holds the weights and
:class:`MissingLPIPS` otherwise, after one log line. The real metric is held outside the module
tree (:class:`DetachedMetric`), so a checkpoint trained offline loads where the weights are cached
and vice versa. How the factory reaches the host differs: nerfstudio 1.x builds the metric inside
our models' ``populate_modules`` (:mod:`sp_plugins.nerfstudio.components.lpips`), sdfstudio by a name bound at
import (:mod:`sp_plugins.patches.sdfstudio_lpips`).
"""

from __future__ import annotations

import logging
import os
from typing import Any, Callable, Optional

import torch

log = logging.getLogger(__name__)

# torchmetrics' ``net_type`` -> torchvision weights enum holding the download URL.
_BACKBONE_WEIGHTS = {"alex": "AlexNet_Weights", "vgg": "VGG16_Weights", "squeeze": "SqueezeNet1_1_Weights"}
_warned: set = set()


def lpips_weights_path(net_type: str = "alex") -> Optional[str]:
    """Where torch hub caches the backbone of ``net_type`` (None when torchvision does not know it)."""
    try:
        import torchvision.models as tvm

        url = getattr(tvm, _BACKBONE_WEIGHTS[net_type]).DEFAULT.url
    except (ImportError, KeyError, AttributeError):
        return None
    return os.path.join(torch.hub.get_dir(), "checkpoints", os.path.basename(url))


def lpips_available(net_type: str = "alex") -> bool:
    path = lpips_weights_path(net_type)
    return path is not None and os.path.isfile(path)


class MissingLPIPS:
    """Stands in for the metric when its weights are not cached: returns NaN, holds no state."""

    available = False

    def __call__(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        return torch.tensor(float("nan"))

    def to(self, *args: Any, **kwargs: Any) -> "MissingLPIPS":
        return self


class DetachedMetric:
    """Holds a metric outside the module tree and moves it to the inputs' device on first use."""

    available = True

    def __init__(self, metric: torch.nn.Module) -> None:
        self.metric = metric

    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        if self.metric.device != a.device:  # torchmetrics Metric tracks its device
            self.metric = self.metric.to(a.device)
        return self.metric(a, b)

    def to(self, *args: Any, **kwargs: Any) -> "DetachedMetric":
        return self


def say_skipped(net_type: str) -> None:
    """The one log line (per backbone and process) that LPIPS is skipped and where its weights go."""
    if net_type not in _warned:
        _warned.add(net_type)
        log.warning(
            "LPIPS skipped (NaN): the %s backbone weights are not in the torch hub cache (%s) and sp-plugins "
            "does not download at run time; copy them there to enable the metric.",
            net_type,
            lpips_weights_path(net_type),
        )


def offline_factory(real_cls: type, detach: bool = False) -> Callable[..., Any]:
    """Stands in for the metric class: the real metric (``detach``: wrapped in
    :class:`DetachedMetric`) when its weights are cached, else :class:`MissingLPIPS`."""

    def build(*args: Any, **kwargs: Any):
        net_type = kwargs.get("net_type", args[0] if args else "alex")
        if lpips_available(net_type):
            metric = real_cls(*args, **kwargs)
            return DetachedMetric(metric) if detach else metric
        say_skipped(net_type)
        return MissingLPIPS()

    setattr(build, "real", real_cls)  # (a function attribute, which a type checker cannot declare)
    return build
