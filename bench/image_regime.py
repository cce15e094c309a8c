"""Image fitting in the paper's regime: a hash grid that cannot hold the photo.

The paper's image table (Instant-NGP 32-42 dB on five photographs; its alpha-map guided adaptive
techniques +0.3 to +0.6 dB on four of them) comes from a grid that is capacity-limited: 16 levels
x 2^19 rows x 2 features for photos of several megapixels, so hash collisions at the fine levels
decide the error. ``bench/image_adaptive.py`` ran 128-px photos with tens of parameters per pixel,
where Instant-NGP fits to 44-60 dB and there is nothing to spend better. Here the photos are crops
at their own resolution (no resizing, so they keep their detail) and the table is sized by
parameters per pixel (``16 levels x 2^T rows x 2 features / pixels``).

Variants (``bench.image_adaptive.make_config``: the paper's schedule scaled to ``--steps``):
``baseline`` (Instant-NGP: Adam 1e-3, x0.6 at 2/3), ``sp`` (+ SP, alpha 0.01 of the side, to 0 over
the first 20%), ``adaptive`` (+ SP with the learned alpha map at 1/16 of the image, Adam 1e-2, for
the first 20%; then importance sampling and level masking guided by the frozen map).

Two studies (resumable: one JSON per run in ``bench/out/image_regime/``)::

    OMP_NUM_THREADS=1 python -m bench.image_regime table    # 2 photos x 3 variants x 3 seeds at T=13 (1 param/pixel)
    OMP_NUM_THREADS=1 python -m bench.image_regime sweep    # hubble, astronaut: T = 11, 13, 15, 17, 3 variants, seed 0
    OMP_NUM_THREADS=1 python -m bench.image_regime report   # summary.md / summary.json, the two figures
    OMP_NUM_THREADS=1 python -m bench.image_regime table --steps 6000   # the same, longer: in steps-6000/, figures *_6000.png

Figures: ``docs/image_regime_maps.png`` (each photo, its learned alpha map, the error maps of the
baseline and the adaptive run) and ``docs/image_regime_sweep.png`` (PSNR against parameters per pixel).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from bench.harness.common import OUT_DIR, machine_info

OUT = OUT_DIR / "image_regime"
DOCS = Path(__file__).resolve().parents[1] / "docs"
CROP = 512
PHOTOS = ("astronaut", "hubble_deep_field")
VARIANTS = ("baseline", "sp", "adaptive")
TABLE_LOG2 = 13
SWEEP_LOG2 = (11, 13, 15, 17)
SWEEP_PHOTOS = ("hubble_deep_field", "astronaut")
STEPS = 2000
BATCH = 2**14
CHECKPOINTS = 8
"""PSNR of the whole image this many times during a run (its convergence curve)."""


def load_crop(name: str, size: int = CROP) -> np.ndarray:
    """The photo at its own resolution, centre-cropped to at most ``size`` x ``size`` (HxWx3 in [0, 1])."""
    import skimage.data

    img = getattr(skimage.data, name)().astype(np.float32) / 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    img = img[..., :3]
    h, w = img.shape[:2]
    top, left = max(0, (h - size) // 2), max(0, (w - size) // 2)
    return np.ascontiguousarray(img[top:top + size, left:left + size])


def config(variant: str, log2: int, seed: int, steps: int):
    """The run's ImageFitConfig: Instant-NGP's image grid (16 levels, 16..2048, 2 features) with 2^log2 rows."""
    from bench.image_adaptive import make_config

    args = SimpleNamespace(size=512, steps=steps, seed=seed, batch=BATCH)
    cfg = make_config(variant, args)
    cfg.encoding.log2_table_size = log2
    return cfg


def params_per_pixel(log2: int, img: np.ndarray, levels: int = 16, features: int = 2) -> float:
    return levels * 2**log2 * features / (img.shape[0] * img.shape[1])


def out_dir(steps: int) -> Path:
    """Where a study of ``steps`` steps keeps its runs: ``OUT`` at the default length, ``OUT/steps-N`` otherwise."""
    return OUT if steps == STEPS else OUT / f"steps-{steps}"


def run(name: str, variant: str, log2: int, seed: int, steps: int) -> dict:
    import torch

    from sp_plugins.tasks.image import psnr, save_image

    torch.set_num_threads(1)
    img = load_crop(name)
    trainer = config(variant, log2, seed, steps).setup(img)
    curve, phase1 = [], None
    every = max(1, steps // CHECKPOINTS)
    start = time.perf_counter()
    while not trainer.done:
        trainer.step()
        if phase1 is None and trainer.phase2_step is not None:
            phase1 = trainer.render()
        if trainer.step_index % every == 0 or trainer.done:
            curve.append([trainer.step_index, psnr(trainer.render(), img)])
    seconds = time.perf_counter() - start
    fitted = trainer.render()
    stem, out = f"{name}_{variant}_T{log2}_s{seed}", out_dir(steps)
    record = dict(image=name, variant=variant, log2_table_size=log2, seed=seed, steps=steps, batch=BATCH,
                  height=img.shape[0], width=img.shape[1], params_per_pixel=params_per_pixel(log2, img),
                  psnr=psnr(fitted, img), curve=curve, seconds=seconds, machine=machine_info())
    save_image(fitted, out / f"{stem}.png")
    if variant == "adaptive" and trainer.sp.alpha_grid is not None:
        np.save(out / f"{stem}_alpha.npy", trainer.pixel_alpha().reshape(trainer.height, trainer.width).cpu().numpy())
        record.update(phase2_step=trainer.phase2_step, psnr_at_phase2_start=psnr(phase1, img) if phase1 is not None else None)
    return record


def jobs(study: str):
    if study == "table":
        return [(p, v, TABLE_LOG2, s) for s in (0, 1, 2) for p in PHOTOS for v in VARIANTS]
    return [(p, v, t, 0) for p in SWEEP_PHOTOS for t in SWEEP_LOG2 for v in VARIANTS]


def late_gain(curve: list) -> float:
    """PSNR gained over the last quarter of a run's steps (how far from converged it stopped)."""
    last_step = curve[-1][0]
    at = min(curve, key=lambda point: abs(point[0] - 0.75 * last_step))
    return curve[-1][1] - at[1]


def records(out: Path) -> list:
    return [json.loads(p.read_text()) for p in sorted(out.glob("*.json")) if not p.name.startswith("summary")]


def report(steps: int = STEPS) -> None:
    from sp_plugins.stats import paired_difference, spread

    out = out_dir(steps)
    rows = records(out)
    find = {(r["image"], r["variant"], r["log2_table_size"], r["seed"]): r for r in rows}
    lines = [f"Main table: {len(PHOTOS)} photos, 2^{TABLE_LOG2} rows per level, {steps} steps of {BATCH} pixels; "
             "PSNR mean ± sd over seeds; differences paired by seed with a 95% t interval.", "",
             "| photo | pixels | params / pixel | Instant-NGP | + SP | + SP + adaptive | SP - NGP | adaptive - NGP | adaptive - SP "
             "| NGP's gain over its last quarter of steps |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    summary: dict = {"table": {}, "sweep": {}}
    for photo in PHOTOS:
        seeds = [s for s in (0, 1, 2) if all((photo, v, TABLE_LOG2, s) in find for v in VARIANTS)]
        if not seeds:
            continue
        vals = {v: [find[(photo, v, TABLE_LOG2, s)]["psnr"] for s in seeds] for v in VARIANTS}
        first = find[(photo, "baseline", TABLE_LOG2, seeds[0])]

        def cell(v):
            m, sd = spread(vals[v])
            return f"{m:.2f}" + (f" ± {sd:.2f}" if sd is not None else "")

        def diff(a, b):
            d = paired_difference(vals[a], vals[b])
            return d.text(2) + (f" ({d.verdict})" if d.low is not None else " (one seed)"), d.as_dict()

        cells = {k: diff(*k) for k in (("baseline", "sp"), ("baseline", "adaptive"), ("sp", "adaptive"))}
        late = [late_gain(find[(photo, "baseline", TABLE_LOG2, s)]["curve"]) for s in seeds]
        lines.append(f"| {photo} | {first['width']}x{first['height']} | {first['params_per_pixel']:.2f} | "
                     + " | ".join(cell(v) for v in VARIANTS) + " | " + " | ".join(c[0] for c in cells.values())
                     + f" | {sum(late) / len(late):+.2f} dB |")
        summary["table"][photo] = {"seeds": seeds, "psnr": vals, "differences": {f"{b} - {a}": c[1] for (a, b), c in cells.items()}}
    for photo in SWEEP_PHOTOS:
        sweep = sorted({r["log2_table_size"] for r in rows if r["image"] == photo and r["seed"] == 0})
        got_all = {t: {v: find.get((photo, v, t, 0)) for v in VARIANTS} for t in sweep}
        sizes = [t for t in sweep if all(got_all[t].values())]
        if len(sizes) < 2:  # a sweep of one table size is the main table's run, no sweep
            continue
        lines += ["", f"Sweep: {photo}, seed 0, PSNR by table size", "",
                  "| rows per level | params / pixel | Instant-NGP | + SP | + SP + adaptive | adaptive - NGP |", "|---|---|---|---|---|---|"]
        for t in sizes:
            got = got_all[t]
            lines.append(f"| 2^{t} | {got['baseline']['params_per_pixel']:.2f} | " + " | ".join(f"{got[v]['psnr']:.2f}" for v in VARIANTS)
                         + f" | {got['adaptive']['psnr'] - got['baseline']['psnr']:+.2f} |")
            summary["sweep"].setdefault(photo, {})[t] = ({v: got[v]["psnr"] for v in VARIANTS}
                                                         | {"params_per_pixel": got["baseline"]["params_per_pixel"]})
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print("\n".join(lines))
    figures(find, summary, out, suffix="" if steps == STEPS else f"_{steps}")


def figures(find: dict, summary: dict, out: Path, suffix: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    photos = [p for p in PHOTOS if (p, "adaptive", TABLE_LOG2, 0) in find and (out / f"{p}_adaptive_T{TABLE_LOG2}_s0_alpha.npy").exists()]
    if photos:
        import imageio.v2 as imageio

        fig, axes = plt.subplots(len(photos), 4, figsize=(13, 3.4 * len(photos)), squeeze=False)
        for row, photo in zip(axes, photos):
            img = load_crop(photo)
            alpha = np.load(out / f"{photo}_adaptive_T{TABLE_LOG2}_s0_alpha.npy")
            errs = [np.abs(imageio.imread(out / f"{photo}_{v}_T{TABLE_LOG2}_s0.png")[..., :3] / 255.0 - img).mean(-1)
                    for v in ("baseline", "adaptive")]
            vmax = max(float(np.quantile(e, 0.99)) for e in errs)
            row[0].imshow(img)
            row[0].set_title(photo.replace("_", " "), fontsize=9)
            im = row[1].imshow(alpha, cmap="magma", norm=LogNorm())
            row[1].set_title("learned alpha (log)", fontsize=9)
            fig.colorbar(im, ax=row[1], fraction=0.046, pad=0.03)
            for ax, err, v in zip(row[2:], errs, ("baseline", "adaptive")):
                r = find[(photo, v, TABLE_LOG2, 0)]
                ax.imshow(err, cmap="inferno", vmin=0, vmax=vmax)
                ax.set_title(f"|error| {'Instant-NGP' if v == 'baseline' else 'SP + adaptive'} ({r['psnr']:.2f} dB)", fontsize=9)
            for ax in row:
                ax.set_axis_off()
        fig.suptitle(f"2^{TABLE_LOG2} rows per level ({find[(photos[0], 'baseline', TABLE_LOG2, 0)]['params_per_pixel']:.2f} "
                     "parameters per pixel), seed 0", fontsize=10)
        fig.tight_layout()
        fig.savefig(DOCS / f"image_regime_maps{suffix}.png", dpi=90)
        plt.close(fig)
    if summary["sweep"]:  # PSNR against parameters per pixel, a panel per photo swept
        photos = list(summary["sweep"])
        fig, axes = plt.subplots(1, len(photos), figsize=(5.5 * len(photos), 3.6), squeeze=False)
        for ax, photo in zip(axes[0], photos):
            sweep = summary["sweep"][photo]
            ts = sorted(sweep)
            x = [sweep[t]["params_per_pixel"] for t in ts]
            for v, label in zip(VARIANTS, ("Instant-NGP", "+ SP", "+ SP + adaptive")):
                ax.plot(x, [sweep[t][v] for t in ts], marker="o", label=label)
            ax.set_xscale("log", base=2)
            ax.set_xlabel("hash-table parameters per pixel")
            ax.set_ylabel("PSNR (dB)")
            ax.set_title(f"{photo.replace('_', ' ')} {CROP}x{CROP}, seed 0", fontsize=9)
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(DOCS / f"image_regime_sweep{suffix}.png", dpi=100)
        plt.close(fig)

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study", choices=("table", "sweep", "both", "report"))
    parser.add_argument("--steps", type=int, default=STEPS)
    args = parser.parse_args()
    out = out_dir(args.steps)
    out.mkdir(parents=True, exist_ok=True)
    if args.study == "report":
        report(args.steps)
        return
    todo = jobs("table") + jobs("sweep") if args.study == "both" else jobs(args.study)
    for photo, variant, log2, seed in todo:
        path = out / f"{photo}_{variant}_T{log2}_s{seed}.json"
        if path.exists():
            continue
        record = run(photo, variant, log2, seed, args.steps)
        path.write_text(json.dumps(record, indent=1))
        print(f"{path.stem}: {record['psnr']:.2f} dB, {record['seconds']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
