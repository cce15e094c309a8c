"""LPIPS that never downloads, under nerfstudio 1.x (see :mod:`sp_plugins.adapter.lpips`).

Every nerfstudio model builds torchmetrics' LPIPS inside ``populate_modules``; :func:`offline_lpips`
(the registry's ``nerfstudio_lpips`` patch) wraps that call, so the metric is built only from cached weights (else :class:`MissingLPIPS`,
after one log line). Models then drop the ``lpips`` key from their image metrics
(:func:`drop_missing_lpips`). Either way the metric is kept out of the model's ``state_dict``
(:func:`detach_lpips`), so a checkpoint trained offline loads where the weights are cached and
vice versa.
"""

from __future__ import annotations

from typing import Any, ContextManager, Dict

import torch

from sp_plugins.adapter.lpips import DetachedMetric, MissingLPIPS, lpips_available, lpips_weights_path
from sp_plugins.patches import registry

__all__ = ["MissingLPIPS", "detach_lpips", "drop_missing_lpips", "lpips_available", "lpips_weights_path", "offline_lpips"]


def offline_lpips() -> ContextManager[None]:
    """Within this block, building torchmetrics' LPIPS never touches the network (the registry's
    ``nerfstudio_lpips`` scope)."""
    return registry.scope("nerfstudio_lpips")


def detach_lpips(model: torch.nn.Module, name: str = "lpips") -> None:
    """Move ``model.<name>`` out of the module tree (so it is not in the state dict)."""
    metric = model._modules.pop(name, None)
    if metric is None:
        metric = model.__dict__.get(name)
    if metric is None or isinstance(metric, (MissingLPIPS, DetachedMetric)):
        return
    setattr(model, name, DetachedMetric(metric))  # a plain attribute: not a submodule any more


def drop_missing_lpips(model: torch.nn.Module, metrics: Dict[str, Any], name: str = "lpips") -> Dict[str, Any]:
    """Remove the LPIPS entries (``lpips``, MipNeRF's ``fine_lpips``...) from image metrics when
    the metric is unavailable."""
    if not getattr(getattr(model, name, None), "available", True):
        for key in [k for k in metrics if k.endswith("lpips")]:
            metrics.pop(key)
    return metrics
