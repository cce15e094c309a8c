"""sdfstudio's models build torchmetrics' LPIPS, which downloads AlexNet weights: offline it fails.

Targets sdfstudio commit 370902a: ``SurfaceModel.populate_modules`` (and the NeRF models) call
``LearnedPerceptualImagePatchSimilarity()``, bound by name at module import. After those modules
execute, the name is replaced by the factory of :mod:`sp_plugins.adapter.lpips`, which builds the
real metric when the backbone weights are in torch hub's cache and otherwise returns
:class:`MissingLPIPS` (NaN, one log line), never downloading. Either way the metric is held outside the module tree, so it is never in a
checkpoint: a checkpoint trained offline loads where the weights are cached and vice versa
(sdfstudio loads checkpoints strictly). Registry entry ``sdfstudio_lpips``: leaving its scope puts
torchmetrics' class back in those modules.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

from sp_plugins.adapter.lpips import MissingLPIPS, lpips_weights_path, offline_factory
from sp_plugins.patches.registry import Patch
from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT, expect_source, patching, sdfstudio_patch

__all__ = ["HOST_COMMIT", "MissingLPIPS", "PATCH", "lpips_weights_path"]

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


def _patch(module, rebind) -> None:
    real = getattr(module, NAME, None)
    if real is not None and not hasattr(real, "real"):
        rebind(module, NAME, offline_factory(real, detach=True))


@contextlib.contextmanager
def offline_lpips_for_sdfstudio() -> Iterator[None]:
    with patching(after={name: _patch for name in MODULES}):
        yield


def _check(patch: Patch) -> None:
    expect_source(patch, "nerfstudio/models/base_surface_model.py", f"from torchmetrics.image.lpip import {NAME}")


PATCH = sdfstudio_patch(
    "sdfstudio_lpips", _check, offline_lpips_for_sdfstudio, "nerfstudio/models/base_surface_model.py",
    changes=f"{NAME} as bound in sdfstudio's model modules: cached weights or a NaN stand-in, never a download, not in the state dict",
    scope_text="those sdfstudio modules; process-wide (those modules) in sp-sdfstudio-* / the hook")
