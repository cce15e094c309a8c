"""The lockstep driver for nerfstudio 1.x: :class:`Run` builds the host's own trainer from a trainer
config (``sp_plugins.nerfstudio.runs`` makes and shrinks those) and measures what it trained."""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Optional, Sequence

import torch

from bench.harness import lockstep, metrics
from bench.harness.lockstep import active_time_ratios, run_summary, step_stats, time_ratio, train_together  # noqa: F401


def _trainer(config):
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="test")
    return trainer


class Run(lockstep.Run):
    """One nerfstudio trainer (``config.setup()``, test split for evaluation) driven step by step."""

    def __init__(self, name: str, config, seed: int) -> None:
        super().__init__(name, lambda: _trainer(config), seed)

    @torch.no_grad()
    def train_psnr(self, max_views: int = 24) -> float:
        """Mean PSNR over (up to ``max_views``) training views: with the test PSNR it tells
        under-determination (train high, test low) from an optimisation failure (both low)."""
        model = self.model
        model.eval()
        dataset = self.trainer.pipeline.datamanager.train_dataset
        psnrs = []
        for i in range(min(max_views, len(dataset))):
            gt = dataset.get_image_float32(i)
            if gt.shape[-1] == 4:  # RGBA (random training background): straight alpha over white
                gt = gt[..., :3] * gt[..., 3:] + (1.0 - gt[..., 3:])
            out = model.get_outputs_for_camera(dataset.cameras[i : i + 1].to(model.device))
            rgb = out["rgb"]
            if getattr(model.config, "background_color", "white") == "random":  # rendered over black
                rgb = rgb + (1.0 - out["accumulation"])
            mse = float(((rgb.clamp(0, 1) - gt) ** 2).mean())
            psnrs.append(-10.0 * math.log10(max(mse, 1e-10)))
        model.train()
        return statistics.mean(psnrs)

    @torch.no_grad()
    def evaluate(self, rgb_key: str = "rgb", acc_key: str = "accumulation", object_masks: Optional[Sequence[Path]] = None) -> dict:
        """Test-view PSNR, SSIM, (LPIPS when cached) and background opacity; keeps the first four
        renders in ``self.renders``. With ``object_masks`` (one image per test view) also the PSNR
        and SSIM inside each mask."""
        import numpy as np
        from PIL import Image
        from torchmetrics.functional import structural_similarity_index_measure as ssim

        from sp_plugins.nerfstudio.components.lpips import lpips_available

        model = self.model
        model.eval()
        dataset = self.trainer.pipeline.datamanager.eval_dataset
        lpips = None
        if lpips_available():
            from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

            lpips = LearnedPerceptualImagePatchSimilarity(normalize=True)
        psnrs, ssims, lps, bg, fg, inside, ssims_inside = [], [], [], [], [], [], []
        renders = []
        for i in range(len(dataset)):
            rgba = np.asarray(Image.open(dataset.image_filenames[i]).convert("RGBA"), dtype=np.float32) / 255.0
            alpha = torch.from_numpy(rgba[..., 3:])
            gt = torch.from_numpy(rgba[..., :3]) * alpha + (1.0 - alpha)  # straight alpha over white
            out = model.get_outputs_for_camera(dataset.cameras[i : i + 1].to(model.device))
            acc = out[acc_key][..., 0]
            rgb = out[rgb_key]
            if getattr(model.config, "background_color", "white") == "random":  # rendered over black
                rgb = rgb + (1.0 - acc[..., None])
            rgb = rgb.clamp(0, 1)
            mse = float(((rgb - gt) ** 2).mean())
            psnrs.append(-10.0 * math.log10(max(mse, 1e-10)))
            if object_masks is not None:
                mask = torch.from_numpy(np.asarray(Image.open(object_masks[i]).convert("L")) > 127)
                inside.append(-10.0 * math.log10(max(float(((rgb - gt)[mask] ** 2).mean()), 1e-10)))
                m = mask[..., None].float()  # RegNeRF / FreeNeRF's masked SSIM on DTU: the background set to 1 in both images
                fg_rgb, fg_gt = (img * m + (1.0 - m) for img in (rgb, gt))
                ssims_inside.append(float(ssim(fg_rgb.permute(2, 0, 1)[None], fg_gt.permute(2, 0, 1)[None], data_range=1.0)))
            a, b = gt.permute(2, 0, 1)[None], rgb.permute(2, 0, 1)[None]
            ssims.append(float(ssim(b, a, data_range=1.0)))
            if lpips is not None:
                lps.append(float(lpips(b, a)))
            empty = alpha[..., 0] == 0
            bg.append(float(acc[empty].mean()) if empty.any() else float("nan"))
            fg.append(float(acc[alpha[..., 0] >= 0.999].mean()))
            if i < 4:
                renders.append((gt, rgb, acc))
        model.train()
        result = {
            "psnr": statistics.mean(psnrs),
            "ssim": statistics.mean(ssims),
            "background_opacity": statistics.mean(bg),
            "foreground_opacity": statistics.mean(fg),
            "psnr_per_view": psnrs,
        }
        if lps:
            result["lpips"] = statistics.mean(lps)
        if inside:
            result["psnr_object"] = statistics.mean(inside)
            result["psnr_object_per_view"] = inside
            result["ssim_object"] = statistics.mean(ssims_inside)
        self.renders = renders
        return result

    def evaluate_sdf(self, gt_mesh_path: Path, mesh_resolution: int, mesh_out: Path) -> dict:
        """nerfstudio's own image metrics on the test split, and the mesh of the SDF in [-1, 1]^3
        against the true mesh (moved as the data parser moved the scene)."""
        from sp_plugins.data import load_gt_mesh

        pipeline = self.trainer.pipeline
        pipeline.eval()
        images = pipeline.get_average_eval_image_metrics()
        mesh = metrics.sdf_mesh(pipeline.model.field, (-1.0, 1.0), mesh_resolution)
        mesh.export(mesh_out)
        gt = load_gt_mesh(gt_mesh_path, pipeline.datamanager.train_dataparser_outputs)
        return {"psnr": float(images["psnr"]), "ssim": float(images["ssim"]), **metrics.geometry(mesh, gt, 100_000)}


def save_renders(runs, path: Path) -> None:
    """Rows: the kept test views; columns: ground truth, then each run's colour and opacity."""
    first = next(iter(runs.values()))
    columns = {name: [(rgb.numpy(), acc.numpy()) for _, rgb, acc in run.renders] for name, run in runs.items()}
    metrics.render_grid(columns, [gt.numpy() for gt, _, _ in first.renders], path)
