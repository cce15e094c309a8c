"""Image fitting: Instant-NGP vs SP vs SP + alpha-map guided adaptive techniques.

Five photographs bundled with scikit-image (no download), resized so the long side is
``--size`` pixels. Every variant uses the same seed, steps, batch and field:

- ``baseline``: Instant-NGP's image setting scaled to the image: 16 levels from 16 to
  ``2048 * size / 512`` (the same cells per pixel as 2048 on a 512-pixel photo), a table of
  ``2^19 * (size / 512)^2`` rows (the same rows per pixel), 2 features, MLP 2x64, Adam 1e-3 x0.6
  at 2/3 of training;
- ``sp``: the same with SP, one global alpha (0.01 of the image side, exponential to 0 over the
  first 20% of training);
- ``adaptive``: phase 1 (first 20%): SP with a learnable alpha map at 1/16 of the image size
  (Adam lr 0.01, init 0.01, no extra schedule); phase 2: the frozen map drives importance
  sampling of pixels and per-pixel level masking (``sp-fit image --adaptive-alpha
  --importance-sampling --level-masking``).

Per run: PSNR of the fitted image, seconds per step and, for ``adaptive``, the learned map and
what it follows: the Spearman rank correlation, over map-cell-sized blocks, of alpha with the
image's gradient magnitude, its local standard deviation, and the gradient magnitude of the
field as fitted at the end of phase 1.

Usage (resumable: one JSON per image/variant in ``bench/out/image_adaptive/``)::

    OMP_NUM_THREADS=1 python -m bench.image_adaptive                 # 5 images x 3 variants
    OMP_NUM_THREADS=1 python -m bench.image_adaptive --images astronaut --steps 300   # a quick look

Writes ``summary.md`` / ``summary.json`` there and the figure ``docs/image_alpha_maps.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from bench.harness.common import OUT_DIR, machine_info

IMAGES = ("astronaut", "chelsea", "coffee", "rocket", "hubble_deep_field")
VARIANTS = ("baseline", "sp", "adaptive")
ABLATIONS = ("adaptive-sampling-only", "adaptive-masking-only")
"""Phase 2 with one technique only (``--variants adaptive-sampling-only ...``): which one moves PSNR."""
FIGURE = Path(__file__).resolve().parents[1] / "docs" / "image_alpha_maps.png"


def load_photo(name: str, size: int) -> np.ndarray:
    import skimage.data
    from skimage.transform import resize

    img = getattr(skimage.data, name)().astype(np.float32) / 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    h, w = img.shape[:2]
    scale = size / max(h, w)
    return resize(img[..., :3], (round(h * scale), round(w * scale)), anti_aliasing=True).astype(np.float32)


def make_config(variant: str, args):
    from sp_plugins import SPConfig
    from sp_plugins.tasks.fields import EncodingConfig
    from sp_plugins.tasks.image import ImageFitConfig

    ratio = args.size / 512
    encoding = EncodingConfig(
        kind="hashgrid", levels=16, features_per_level=2, log2_table_size=round(19 + 2 * math.log2(ratio)),
        base_resolution=16, max_resolution=round(2048 * ratio),
    )
    common = dict(steps=args.steps, seed=args.seed, batch=args.batch, lr=1e-3, lr_decay=0.6, lr_decay_at=2 / 3,
                  hidden=(64, 64), encoding=encoding)
    if variant == "baseline":
        return ImageFitConfig(**common, sp=SPConfig(enabled=False))
    if variant == "sp":
        return ImageFitConfig(**common, sp=SPConfig(alpha0=0.01, schedule="exponential", end=0.2))
    return ImageFitConfig(
        **common, sp=SPConfig(alpha0=0.01, schedule="step", end=0.2), adaptive_alpha=True, alpha_map_downscale=16,
        alpha_map_lr=0.01, importance_sampling=variant != "adaptive-masking-only",
        level_masking=variant != "adaptive-sampling-only",
    )


def block_mean(a: np.ndarray, block: int) -> np.ndarray:
    h, w = (a.shape[0] // block) * block, (a.shape[1] // block) * block
    return a[:h, :w].reshape(h // block, block, w // block, block).mean(axis=(1, 3))


def gradient_magnitude(rgb: np.ndarray) -> np.ndarray:
    from skimage.filters import sobel

    return sobel(rgb.mean(axis=-1))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(a.reshape(-1), b.reshape(-1)).statistic)


def run_one(name: str, variant: str, args, out_dir: Path) -> dict:
    import torch

    torch.set_num_threads(1)
    img = load_photo(name, args.size)
    trainer = make_config(variant, args).setup(img)
    start = time.perf_counter()
    phase1_render = None
    while not trainer.done:
        trainer.step()
        if phase1_render is None and trainer.phase2_step is not None:
            phase1_render = trainer.render()
    seconds = time.perf_counter() - start
    fitted = trainer.render()
    from sp_plugins.tasks.image import psnr, save_image

    record = dict(image=name, variant=variant, height=trainer.height, width=trainer.width, psnr=psnr(fitted, img),
                  seconds=seconds, seconds_per_step=trainer.timer.total / trainer.step_index, steps=trainer.step_index,
                  final_loss=trainer.history["loss"][-1], machine=machine_info())
    save_image(fitted, out_dir / f"{name}_{variant}.png")
    if trainer.sp.alpha_grid is not None:
        alpha = trainer.pixel_alpha().reshape(trainer.height, trainer.width).cpu().numpy()
        if variant == "adaptive":
            np.save(out_dir / f"{name}_alpha.npy", alpha)
        block = trainer.config.alpha_map_downscale  # one map cell
        log_alpha = np.log(block_mean(alpha, block))
        grad_img = block_mean(gradient_magnitude(img), block)
        gray = img.mean(axis=-1)
        local_std = np.sqrt(np.maximum(block_mean(gray**2, block) - block_mean(gray, block) ** 2, 0.0))
        grad_fit = block_mean(gradient_magnitude(phase1_render), block)
        values = trainer.sp.alpha_grid.values().cpu().numpy()
        record.update(
            alpha_map_resolution=list(values.shape[::-1]), alpha_init=trainer.config.sp.alpha0,
            alpha_min=float(values.min()), alpha_max=float(values.max()), alpha_median=float(np.median(values)),
            fraction_of_cells_below_init=float(np.mean(values < trainer.config.sp.alpha0)),
            spearman_alpha_vs_image_gradient=spearman(log_alpha, grad_img),
            spearman_alpha_vs_local_std=spearman(log_alpha, local_std),
            spearman_alpha_vs_fitted_gradient=spearman(log_alpha, grad_fit),
            level_mask_alpha_range=list(trainer.level_mask_alpha_range or ()), phase2_step=trainer.phase2_step,
            psnr_at_phase2_start=psnr(phase1_render, img),
        )
    return record


def write_summary(args, out_dir: Path) -> None:
    rows = {}
    for path in sorted(out_dir.glob("*.json")):
        if path.name.startswith("summary"):
            continue
        r = json.loads(path.read_text())
        rows.setdefault(r["image"], {})[r["variant"]] = r
    lines = ["| image | size | baseline PSNR | SP PSNR | SP + adaptive PSNR | adaptive - baseline | adaptive - SP | "
             "alpha min..max | rho(alpha, image grad) | rho(alpha, local std) | rho(alpha, fitted grad) | s/step b / sp / a |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in args.images:
        r = rows.get(name, {})
        if len(r) < 3:
            continue
        b, s, a = r["baseline"], r["sp"], r["adaptive"]
        lines.append(
            f"| {name} | {a['width']}x{a['height']} | {b['psnr']:.2f} | {s['psnr']:.2f} | {a['psnr']:.2f} | "
            f"{a['psnr'] - b['psnr']:+.2f} | {a['psnr'] - s['psnr']:+.2f} | {a['alpha_min']:.4f}..{a['alpha_max']:.4f} | "
            f"{a['spearman_alpha_vs_image_gradient']:+.2f} | {a['spearman_alpha_vs_local_std']:+.2f} | "
            f"{a['spearman_alpha_vs_fitted_gradient']:+.2f} | "
            f"{b['seconds_per_step']:.3f} / {s['seconds_per_step']:.3f} / {a['seconds_per_step']:.3f} |"
        )
    ablation = [f"| {name} | {r['adaptive']['psnr']:.2f} | " + " | ".join(f"{r[v]['psnr']:.2f}" for v in ABLATIONS) + " |"
                for name, r in rows.items() if "adaptive" in r and all(v in r for v in ABLATIONS)]
    if ablation:
        lines += ["", "| image | sampling + masking | sampling only | masking only |", "|---|---|---|---|"] + ablation
    (out_dir / "summary.md").write_text("\n".join(lines) + "\n")
    (out_dir / "summary.json").write_text(json.dumps(rows, indent=2))
    print("\n".join(lines))
    make_figure([n for n in args.images if (out_dir / f"{n}_alpha.npy").exists()], args, out_dir)


def make_figure(names, args, out_dir: Path) -> None:
    if not names:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(names), figsize=(2.6 * len(names), 5.0), squeeze=False)
    for i, name in enumerate(names):
        img = load_photo(name, args.size)
        alpha = np.load(out_dir / f"{name}_alpha.npy")
        axes[0, i].imshow(img)
        axes[0, i].set_title(name.replace("_", " "), fontsize=9)
        im = axes[1, i].imshow(alpha, cmap="magma", norm=matplotlib.colors.LogNorm())
        fig.colorbar(im, ax=axes[1, i], fraction=0.046, pad=0.03)
        for ax in axes[:, i]:
            ax.set_axis_off()
    axes[1, 0].text(-0.08, 0.5, "learned alpha (log)", transform=axes[1, 0].transAxes, rotation=90, va="center", ha="right", fontsize=9)
    fig.suptitle(f"learned alpha maps after phase 1 ({args.steps // 5} of {args.steps} steps)\n"
                 "dark: low alpha (detail; more samples, all levels), bright: high alpha (fewer levels)", fontsize=9)
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=110)
    plt.close(fig)
    print(f"figure -> {FIGURE}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--images", nargs="+", default=list(IMAGES), choices=IMAGES)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS + ABLATIONS)
    parser.add_argument("--size", type=int, default=128, help="long side of the resized photographs (pixels)")
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--out", type=Path, default=OUT_DIR / "image_adaptive")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.images:
        for variant in args.variants:
            path = args.out / f"{name}_{variant}.json"
            if path.exists() and not args.overwrite:
                continue
            record = run_one(name, variant, args, args.out)
            record["args"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
            path.write_text(json.dumps(record, indent=2))
            print(f"{name} {variant}: PSNR {record['psnr']:.2f} dB, {record['seconds_per_step']:.3f} s/step", flush=True)
        write_summary(args, args.out)


if __name__ == "__main__":
    main()
