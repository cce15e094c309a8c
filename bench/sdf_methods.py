"""SDF methods in nerfstudio: baseline vs SP, trained side by side in one process.

Pairs: ``neus-hashgrid`` vs ``sp-neus-hashgrid`` and ``neuralangelo-lite`` vs
``sp-neuralangelo-lite``, on synthetic scenes rendered by :func:`sp_plugins.data.make_scene`
(Blender layout: train / test splits), at a CPU-sized budget. Both runs of a pair start from the
same weights and see the same rays at every step (the RNG is re-seeded per step); their
iterations alternate, so the per-step time ratio is measured under the same machine load.

Per run: test PSNR / SSIM (all test views, nerfstudio's own metric code), Chamfer distance and
normal consistency of a 128^3 marching-cubes mesh against the true mesh
(:func:`sp_plugins.geometry.mesh_metrics`, in units of the true mesh's bounding-box diagonal),
the median seconds per training step, and the loss curve.

Usage::

    python -m bench.sdf_methods                       # every scene x pair x seed not done yet
    python -m bench.sdf_methods --scenes spot --pairs neus --steps 300   # a quick look
    python -m bench.sdf_methods --overwrite           # recompute finished runs

Results (one JSON per scene/pair/seed, resumable) go to ``bench/out/sdf_methods/``; a summary
``sdf_methods.json`` / ``.md`` and a loss-curve PNG next to them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import statistics
import time
from pathlib import Path
from typing import Dict, List

import torch

from bench.common import OUT_DIR, machine_info, seed_everything

PAIRS = {
    "neus": ("neus-hashgrid", "sp-neus-hashgrid"),
    "neuralangelo": ("neuralangelo-lite", "sp-neuralangelo-lite"),
    # the paper's two Neuralangelo variants: the annealed scalar vs the learned alpha grid (issue 37)
    "neuralangelo-grid": ("sp-neuralangelo-lite", "sp-neuralangelo-lite+grid"),
}
"""Pairs of registered methods; ``+grid`` is the method with ``--pipeline.model.sp.alpha-grid True``."""
SCENES = {"spot": "spot", "bunny": "/work/shared/data/meshes/bunny.ply", "torus": "torus"}


@dataclasses.dataclass
class Budget:
    """The CPU-sized setting (shared by every run; stated in the results)."""

    steps: int = 400
    rays: int = 256
    num_samples: int = 32
    num_samples_importance: int = 16
    num_up_sample_steps: int = 2
    hidden_dim: int = 64
    geo_feat_dim: int = 31
    num_levels: int = 16
    max_res: int = 256
    log2_hashmap_size: int = 16
    lr: float = 5e-3
    warm_up_end: int = 100
    views: int = 24
    test_views: int = 4
    resolution: int = 64
    mesh_resolution: int = 128
    c2f_init_levels: int = 4


def make_config(name: str, data: Path, out: Path, budget: Budget, seed: int):
    from sp_plugins.nerfstudio.runs import configure_run, method_config

    method, _, variant = name.partition("+")
    config = method_config(method)
    model = config.pipeline.model
    if variant == "grid":
        model.sp.alpha_grid = True
    field = model.sdf_field
    field.hidden_dim = budget.hidden_dim
    field.hidden_dim_color = budget.hidden_dim
    field.geo_feat_dim = budget.geo_feat_dim
    field.num_levels = budget.num_levels
    field.max_res = budget.max_res
    field.log2_hashmap_size = budget.log2_hashmap_size
    field.bias = 0.5
    model.num_samples = budget.num_samples
    model.num_samples_importance = budget.num_samples_importance
    model.num_up_sample_steps = budget.num_up_sample_steps
    model.background_model = "none"  # synthetic objects on white
    model.background_color = "white"
    model.eval_num_rays_per_chunk = 1024
    model.sp.seed = seed
    if hasattr(model, "c2f_init_levels"):
        model.c2f_init_levels = budget.c2f_init_levels
    for group in ("fields", "field_grid", "field_background"):  # field_grid: the hash-grid tables (same settings)
        opt = config.optimizers[group]
        opt["optimizer"].lr = budget.lr
        opt["scheduler"].warm_up_end = budget.warm_up_end
        opt["scheduler"].max_steps = budget.steps
    configure_run(config, data, steps=budget.steps, output_dir=out, layout="blender", rays_per_batch=budget.rays,
                  experiment_name=f"{name}-seed{seed}")
    return config


class Run:
    """One trainer driven step by step (the loop of ``Trainer.train`` without its extras)."""

    def __init__(self, config, seed: int) -> None:
        from nerfstudio.engine.callbacks import TrainingCallbackLocation

        self.where = TrainingCallbackLocation
        seed_everything(seed)  # the cached image order comes from Python's random (host's CacheDataloader)
        self.trainer = config.setup(local_rank=0, world_size=1)
        self.trainer.setup(test_mode="test")
        self.losses: List[float] = []
        self.times: List[float] = []

    def step(self, step: int, seed: int) -> None:
        trainer = self.trainer
        trainer.pipeline.train()
        for cb in trainer.callbacks:
            cb.run_callback_at_location(step, self.where.BEFORE_TRAIN_ITERATION)
        seed_everything(seed * 1_000_003 + step)  # same rays and jitter for both runs of a pair
        t0 = time.perf_counter()
        loss, _, _ = trainer.train_iteration(step)
        self.times.append(time.perf_counter() - t0)
        for cb in trainer.callbacks:
            cb.run_callback_at_location(step, self.where.AFTER_TRAIN_ITERATION)
        self.losses.append(float(loss))

    def evaluate(self, gt_mesh_path: Path, mesh_resolution: int, mesh_out: Path) -> dict:
        from sp_plugins.data import load_gt_mesh
        from sp_plugins.geometry import extract_mesh, mesh_metrics

        pipeline = self.trainer.pipeline
        pipeline.eval()
        images = pipeline.get_average_eval_image_metrics()
        field = pipeline.model.field
        mesh = extract_mesh(lambda x: field.forward_geonetwork(x)[:, 0], bounds=(-1.0, 1.0), resolution=mesh_resolution, chunk=1 << 16)
        mesh.export(mesh_out)
        gt = load_gt_mesh(gt_mesh_path, pipeline.datamanager.train_dataparser_outputs)
        geometry = mesh_metrics(mesh, gt, n_points=100_000)
        return {
            "psnr": float(images["psnr"]),
            "ssim": float(images["ssim"]),
            "chamfer": geometry["chamfer"],
            "accuracy": geometry["accuracy"],
            "completeness": geometry["completeness"],
            "normal_consistency": geometry["normal_consistency"],
            "fscore": geometry["fscore"],
            "area_ratio": geometry["area_ratio"],
        }


def run_pair(scene: str, pair: str, seed: int, budget: Budget, out: Path) -> dict:
    from sp_plugins.data import make_scene

    scene_dir = out / "scenes" / scene
    if not (scene_dir / "scene.json").is_file():
        make_scene(SCENES[scene], scene_dir, n_train=budget.views, n_val=2, n_test=budget.test_views,
                   resolution=budget.resolution, layouts=("blender",), seed=0, overwrite=True)
    runs: Dict[str, Run] = {}
    for name in PAIRS[pair]:
        runs[name] = Run(make_config(name, scene_dir / "blender", out / "runs" / scene, budget, seed), seed)
    t_start = time.time()
    names = list(runs)
    for step in range(budget.steps):
        for name in names if step % 2 == 0 else names[::-1]:
            runs[name].step(step, seed)
        if step % 100 == 0:
            logging.info("%s/%s seed %d step %d: %s", scene, pair, seed, step,
                         ", ".join(f"{n} {r.losses[-1]:.4f}" for n, r in runs.items()))
    train_wall = time.time() - t_start
    result = {"scene": scene, "pair": pair, "seed": seed, "budget": dataclasses.asdict(budget), "train_wall_s": train_wall}
    base, sp = names
    for name, run in runs.items():
        metrics = run.evaluate(scene_dir / "gt_mesh.ply", budget.mesh_resolution, out / "runs" / scene / f"{name}-seed{seed}.ply")
        skip = min(10, len(run.times) // 10)
        metrics["median_step_s"] = statistics.median(run.times[skip:])
        metrics["final_loss"] = statistics.mean(run.losses[-20:])
        metrics["losses"] = run.losses
        result[name] = metrics
    pairs = [s / b for s, b in zip(runs[sp].times[10:], runs[base].times[10:])]
    result["sp_time_ratio"] = statistics.median(pairs)
    result["machine"] = machine_info()
    return result


def summarise(results: List[dict], out: Path) -> str:
    lines = [
        "| scene | pair | seed | method | test PSNR | SSIM | Chamfer | normal cons. | F-score | area ratio | s/step |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for name in PAIRS[r["pair"]]:
            m = r[name]
            lines.append(
                f"| {r['scene']} | {r['pair']} | {r['seed']} | {name} | {m['psnr']:.2f} | {m['ssim']:.3f} | "
                f"{m['chamfer']:.4f} | {m['normal_consistency']:.3f} | {m['fscore']:.3f} | {m['area_ratio']:.2f} | "
                f"{m['median_step_s']:.3f} |"
            )
    lines.append("")
    lines.append("| scene | pair | seed | SP per-step time ratio (median of alternating pairs) |")
    lines.append("|---|---|---|---|")
    for r in results:
        lines.append(f"| {r['scene']} | {r['pair']} | {r['seed']} | {r['sp_time_ratio']:.3f} |")
    table = "\n".join(lines)
    (out / "sdf_methods.md").write_text(table + "\n")
    (out / "sdf_methods.json").write_text(json.dumps([{k: v for k, v in r.items()} for r in results], indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, max(1, len(results)), figsize=(4 * max(1, len(results)), 3), squeeze=False)
        for ax, r in zip(axes[0], results):
            for name in PAIRS[r["pair"]]:
                losses = torch.tensor(r[name]["losses"])
                k = 25
                smooth = torch.nn.functional.avg_pool1d(losses[None, None], k, 1)[0, 0] if len(losses) > k else losses
                ax.plot(smooth.numpy(), label=name)
            ax.set_title(f"{r['scene']} / {r['pair']} / seed {r['seed']}", fontsize=8)
            ax.set_yscale("log")
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "sdf_methods_loss.png", dpi=100)
        plt.close(fig)
    except Exception as err:  # a plot is a convenience, never a reason to lose results
        logging.warning("loss plot skipped: %s", err)
    return table


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["spot", "bunny"], choices=sorted(SCENES))
    parser.add_argument("--pairs", nargs="+", default=list(PAIRS), choices=sorted(PAIRS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--steps", type=int, default=Budget.steps)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 on a shared machine)")
    parser.add_argument("--out", type=Path, default=OUT_DIR / "sdf_methods")
    parser.add_argument("--overwrite", action="store_true", help="recompute runs that already have results")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    for noisy in ("nerfstudio", "PIL"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    budget = Budget(steps=args.steps)
    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for scene in args.scenes:
        for pair in args.pairs:
            for seed in args.seeds:
                path = args.out / f"{scene}_{pair}_seed{seed}_steps{budget.steps}.json"
                if path.is_file() and not args.overwrite:
                    logging.info("done already: %s", path.name)
                    results.append(json.loads(path.read_text()))
                    continue
                result = run_pair(scene, pair, seed, budget, args.out)
                path.write_text(json.dumps(result, indent=1))
                results.append(result)
                logging.info("wrote %s", path)
    # the summary covers every finished run at this budget, not only the ones asked for now
    done = sorted(args.out.glob(f"*_steps{budget.steps}.json"))
    results = [json.loads(p.read_text()) for p in done]
    results.sort(key=lambda r: (r["scene"], r["pair"], r["seed"]))
    print(summarise(results, args.out))
    print(f"\nbudget: {dataclasses.asdict(budget)}\nmachine: {machine_info()}")


if __name__ == "__main__":
    main()
