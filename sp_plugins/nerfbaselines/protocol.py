"""The evaluation protocol of ``sp-scene`` datasets: nerfbaselines' ``default`` protocol (PSNR, SSIM,
MAE, MSE, LPIPS-alex on sRGB uint8 images, the same code), with LPIPS never downloading its backbone
(the registry's ``nerfbaselines_lpips`` scope around each image's metrics), so ``nerfbaselines
evaluate`` on renders of our scenes finishes offline with PSNR and SSIM and one line about LPIPS.
"""

from __future__ import annotations

from nerfbaselines.evaluation import DefaultEvaluationProtocol

from sp_plugins.patches import registry

__all__ = ["SceneProtocol"]


class SceneProtocol(DefaultEvaluationProtocol):
    _name = "sp-scene"

    def evaluate(self, predictions, dataset):
        with registry.scope("nerfbaselines_lpips"):
            return super().evaluate(predictions, dataset)
