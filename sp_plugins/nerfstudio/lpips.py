"""LPIPS that never downloads: the real metric when its backbone weights are cached, else a stub.

Every nerfstudio model builds torchmetrics' LPIPS inside ``populate_modules``; its constructor
fetches the ImageNet backbone from the network. :func:`offline_lpips` wraps that call: while it
is active the constructor first looks for the weights in torch hub's cache and, when they are
missing, returns :class:`MissingLPIPS` after one log line. Models then drop the ``lpips`` key
from their image metrics (:func:`drop_missing_lpips`).

Either way the metric is kept out of the model's ``state_dict`` (:func:`detach_lpips`), so a
checkpoint trained offline loads where the weights are cached and vice versa.
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Any, Dict, Iterator, Optional

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


class _DetachedMetric:
    """Holds a metric outside the module tree and moves it to the inputs' device on first use."""

    available = True

    def __init__(self, metric: torch.nn.Module) -> None:
        self.metric = metric

    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        if self.metric.device != a.device:  # torchmetrics Metric tracks its device
            self.metric = self.metric.to(a.device)
        return self.metric(a, b)


def _guarded_factory(real_cls):
    def build(*args: Any, **kwargs: Any):
        net_type = kwargs.get("net_type", args[0] if args else "alex")
        if lpips_available(net_type):
            return real_cls(*args, **kwargs)
        if net_type not in _warned:
            _warned.add(net_type)
            log.warning(
                "LPIPS skipped: the %s backbone weights are not in the torch hub cache (%s) and sp-plugins "
                "does not download at run time; copy them there to enable the metric.",
                net_type,
                lpips_weights_path(net_type),
            )
        return MissingLPIPS()

    return build


@contextlib.contextmanager
def offline_lpips() -> Iterator[None]:
    """Within this block, building torchmetrics' LPIPS never touches the network."""
    import torchmetrics.image.lpip as lpip_module

    real = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = _guarded_factory(real)  # type: ignore[assignment]
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = real  # type: ignore[assignment]


def detach_lpips(model: torch.nn.Module, name: str = "lpips") -> None:
    """Move ``model.<name>`` out of the module tree (so it is not in the state dict)."""
    metric = model._modules.pop(name, None)
    if metric is None:
        metric = model.__dict__.get(name)
    if metric is None or isinstance(metric, (MissingLPIPS, _DetachedMetric)):
        return
    object.__setattr__(model, name, _DetachedMetric(metric))


def drop_missing_lpips(model: torch.nn.Module, metrics: Dict[str, Any], name: str = "lpips") -> Dict[str, Any]:
    """Remove the LPIPS entries (``lpips``, MipNeRF's ``fine_lpips``...) from image metrics when
    the metric is unavailable."""
    if not getattr(getattr(model, name, None), "available", True):
        for key in [k for k in metrics if k.endswith("lpips")]:
            metrics.pop(key)
    return metrics
