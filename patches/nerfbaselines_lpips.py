"""nerfbaselines' LPIPS without a download (registry entry ``nerfbaselines_lpips``).

nerfbaselines 1.2.x computes LPIPS in ``nerfbaselines.metrics._lpips`` with its own copy of the LPIPS
network, whose backbone (``torchvision`` AlexNet or VGG16, ImageNet weights) torch hub downloads the
first time: offline that fails (here at once; behind a firewall it can hang on a TCP timeout). For the
block, ``_lpips`` is a function that runs the real one when torch hub's cache holds the backbone and
otherwise returns NaN, after one log line naming the file and where it goes. PSNR and SSIM are not
touched. Scope: while one of our nerfbaselines methods exists (``nerfbaselines train`` / ``render``
with an sp-plugins method); nerfbaselines' own methods and its ``evaluate`` command are left as they are.
"""

from __future__ import annotations

import contextlib
import inspect
from typing import Iterator

from sp_plugins.patches.registry import Patch, host_version, swapped

__all__ = ["PATCH", "offline_lpips"]

MODULE = "nerfbaselines.metrics"
NAME = "_lpips"


@contextlib.contextmanager
def offline_lpips() -> Iterator[None]:
    import numpy as np
    import nerfbaselines.metrics as metrics

    from sp_plugins.adapter.lpips import lpips_available, say_skipped  # defers torch (entries() imports every patch)

    real = getattr(metrics, NAME)

    def offline(a, b, net, version="0.1"):
        if lpips_available(net):
            return real(a, b, net, version)
        say_skipped(net)  # (once per backbone and process, also when a model's own metric said it)
        return np.full(a.shape[:-3], np.nan, dtype=np.float32)

    offline.real = real  # type: ignore[attr-defined]
    with swapped(metrics, NAME, offline):
        yield


def _found() -> str:
    return host_version("nerfbaselines")


def _check(patch: Patch) -> None:
    import nerfbaselines.metrics as metrics

    real = getattr(metrics, NAME, None)
    patch.expect(inspect.isfunction(real), f"{MODULE}.{NAME} a function", f"{MODULE}.{NAME} = {type(real).__name__}")
    params = list(inspect.signature(real).parameters)
    patch.expect(params[:3] == ["a", "b", "net"], f"{NAME}(a, b, net, ...)", f"{NAME}{inspect.signature(real)}")
    patch.expect(getattr(metrics, "lpips_alex", None) is not None and "_lpips(" in inspect.getsource(metrics.lpips_alex),
                 "lpips_alex calling _lpips", "another lpips_alex")


PATCH = Patch(
    name="nerfbaselines_lpips",
    host="nerfbaselines",
    version="1.2.12",
    changes=f"{MODULE}.{NAME}: the real LPIPS when its backbone is in torch hub's cache, else NaN after one line; never downloads",
    scope_text="while one of our nerfbaselines methods exists (train, render)",
    check=_check,
    enter=offline_lpips,
    guarded=((MODULE, NAME),),
    found=_found,
)
