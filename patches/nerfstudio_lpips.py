"""LPIPS that never downloads while our nerfstudio models build (registry entry ``nerfstudio_lpips``).

nerfstudio 1.x models build torchmetrics' ``LearnedPerceptualImagePatchSimilarity`` inside
``populate_modules`` (imported there from ``torchmetrics.image.lpip``), and its constructor fetches
an ImageNet backbone from the network: offline it fails. For the block, the module attribute is
:func:`sp_plugins.adapter.lpips.offline_factory` around the real class: the real metric when torch
hub's cache holds the weights, else :class:`~sp_plugins.adapter.lpips.MissingLPIPS` (NaN, one log
line). Scope: our model's ``populate_modules`` (and ``sp-gpu-check``'s builds); after it the
attribute is the real class again, so another method's model builds torchmetrics' own metric.
"""

from __future__ import annotations

import contextlib
import inspect
from typing import Iterator

from sp_plugins.patches.registry import Patch, swapped

__all__ = ["PATCH", "offline_lpips"]

MODULE = "torchmetrics.image.lpip"
NAME = "LearnedPerceptualImagePatchSimilarity"


@contextlib.contextmanager
def offline_lpips() -> Iterator[None]:
    """Within this block, building torchmetrics' LPIPS never touches the network."""
    import torchmetrics.image.lpip as lpip_module

    from sp_plugins.adapter.lpips import offline_factory  # defers torch (entries() imports every patch)

    with swapped(lpip_module, NAME, offline_factory(getattr(lpip_module, NAME))):
        yield


def _check(patch: Patch) -> None:
    import torchmetrics.image.lpip as lpip_module

    real = getattr(lpip_module, NAME, None)
    patch.expect(inspect.isclass(real), f"{MODULE}.{NAME} a class", f"{MODULE}.{NAME} = {type(real).__name__}")
    params = inspect.signature(real.__init__).parameters
    patch.expect("net_type" in params, f"{NAME}(net_type=...)", f"{NAME}{inspect.signature(real.__init__)}")


PATCH = Patch(
    name="nerfstudio_lpips",
    host="torchmetrics",
    version="1.9.0",
    changes=f"{MODULE}.{NAME}: the real metric from cached weights, else a NaN stand-in; never downloads",
    scope_text="our nerfstudio model's populate_modules (and sp-gpu-check's model builds)",
    check=_check,
    enter=offline_lpips,
    guarded=((MODULE, NAME),),
)
