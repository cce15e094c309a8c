"""SDF methods in nerfstudio: baseline vs SP, trained side by side in one process.

Pairs: ``neus-hashgrid`` vs ``sp-neus-hashgrid`` and ``neuralangelo-lite`` vs
``sp-neuralangelo-lite``, on synthetic scenes rendered by :func:`sp_plugins.data.make_scene`
(Blender layout: train / test splits), at a CPU-sized budget. Both runs of a pair start from the
same weights and see the same rays at every step (the RNG is re-seeded per step); their
iterations alternate, so the per-step time ratio is measured under the same machine load
(``bench.harness.lockstep``).

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
from pathlib import Path
from typing import List

from bench.harness import nerfstudio as ns
from bench.harness.common import OUT_DIR, NeuSBudget, done_or_run, machine_info, start
from bench.harness.metrics import loss_figure, table
from bench.harness.scenes import mesh_source, synthetic

PAIRS = {
    "neus": ("neus-hashgrid", "sp-neus-hashgrid"),
    "neuralangelo": ("neuralangelo-lite", "sp-neuralangelo-lite"),
    # the paper's two Neuralangelo variants: the annealed scalar vs the learned alpha grid
    "neuralangelo-grid": ("sp-neuralangelo-lite", "sp-neuralangelo-lite+grid"),
}
"""Pairs of registered methods; ``+grid`` is the method with ``--pipeline.model.sp.alpha-grid True``."""
SCENES = {"spot": "spot", "bunny": mesh_source("bunny"), "torus": "torus"}


@dataclasses.dataclass
class Budget(NeuSBudget):
    """The CPU-sized setting (shared by every run; stated in the results)."""

    num_samples: int = 32
    """NeuS samples per ray before up-sampling"""
    num_samples_importance: int = 16
    """samples added per up-sampling round"""
    num_up_sample_steps: int = 2
    """up-sampling rounds"""
    test_views: int = 4
    """held-out views scored"""
    c2f_init_levels: int = 4
    """hash levels open at the start (coarse-to-fine methods only)"""


def make_config(name: str, data: Path, out: Path, budget: Budget, seed: int):
    from sp_plugins.adapter.shrink import shrink
    from sp_plugins.nerfstudio.runs import configure_run, method_config

    method, _, variant = name.partition("+")
    config = method_config(method)
    model = config.pipeline.model
    if variant == "grid":
        model.sp.alpha_grid = True
    model.sp.seed = seed
    if hasattr(model, "c2f_init_levels"):
        model.c2f_init_levels = budget.c2f_init_levels
    b = budget
    shrink(config, field=dict(**b.field_settings(), bias=0.5),
           num_samples=b.num_samples, num_samples_importance=b.num_samples_importance, num_up_sample_steps=b.num_up_sample_steps,
           background_model="none", background_color="white",  # synthetic objects on white
           eval_num_rays_per_chunk=1024,
           lr=dict.fromkeys(("fields", "field_grid", "field_background"), b.lr),  # field_grid: the hash-grid tables
           warm_up_end=b.warm_up_end, max_steps=b.steps)
    configure_run(config, data, steps=b.steps, output_dir=out, layout="blender", rays_per_batch=b.rays,
                  experiment_name=f"{name}-seed{seed}")
    return config


def run_pair(scene: str, pair: str, seed: int, budget: Budget, out: Path) -> dict:
    scene_dir = synthetic(SCENES[scene], out / "scenes" / scene, views=budget.views, test_views=budget.test_views,
                          resolution=budget.resolution)
    runs = {name: ns.Run(name, make_config(name, scene_dir / "blender", out / "runs" / scene, budget, seed), seed)
            for name in PAIRS[pair]}
    train_wall = ns.train_together(runs, budget.steps, seed, f"{scene}/{pair} seed {seed}")
    result = {"scene": scene, "pair": pair, "seed": seed, "budget": dataclasses.asdict(budget), "train_wall_s": train_wall}
    for name, run in runs.items():
        mesh_out = out / "runs" / scene / f"{name}-seed{seed}.ply"
        result[name] = {**run.evaluate_sdf(scene_dir / "gt_mesh.ply", budget.mesh_resolution, mesh_out), **ns.step_stats(run)}
    base, sp = runs.values()
    result["sp_time_ratio"] = ns.time_ratio(sp, base)
    result["machine"] = machine_info()
    return result


def summarise(results: List[dict], out: Path) -> str:
    runs = [(r, name, r[name]) for r in results for name in PAIRS[r["pair"]]]
    text = table(["scene", "pair", "seed", "method", "test PSNR", "SSIM", "Chamfer", "normal cons.", "F-score", "area ratio", "s/step"],
                 [(r["scene"], r["pair"], r["seed"], name, f"{m['psnr']:.2f}", f"{m['ssim']:.3f}", f"{m['chamfer']:.4f}",
                   f"{m['normal_consistency']:.3f}", f"{m['fscore']:.3f}", f"{m['area_ratio']:.2f}", f"{m['median_step_s']:.3f}")
                  for r, name, m in runs])
    text += "\n\n" + table(["scene", "pair", "seed", "SP per-step time ratio (median of alternating pairs)"],
                           [(r["scene"], r["pair"], r["seed"], f"{r['sp_time_ratio']:.3f}") for r in results])
    (out / "sdf_methods.md").write_text(text + "\n")
    (out / "sdf_methods.json").write_text(json.dumps([{k: v for k, v in r.items()} for r in results], indent=1))
    loss_figure([(f"{r['scene']} / {r['pair']} / seed {r['seed']}", {n: r[n]["losses"] for n in PAIRS[r["pair"]]})
                 for r in results], out / "sdf_methods_loss.png")
    return text


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
    start(args.threads)
    budget = Budget(steps=args.steps)
    args.out.mkdir(parents=True, exist_ok=True)
    for scene in args.scenes:
        for pair in args.pairs:
            for seed in args.seeds:
                path = args.out / f"{scene}_{pair}_seed{seed}_steps{budget.steps}.json"
                done_or_run(path, args.overwrite, lambda: run_pair(scene, pair, seed, budget, args.out))
    # the summary covers every finished run at this budget, not only the ones asked for now
    done = sorted(args.out.glob(f"*_steps{budget.steps}.json"))
    results = [json.loads(p.read_text()) for p in done]
    results.sort(key=lambda r: (r["scene"], r["pair"], r["seed"]))
    print(summarise(results, args.out))
    print(f"\nbudget: {dataclasses.asdict(budget)}\nmachine: {machine_info()}")


if __name__ == "__main__":
    main()
