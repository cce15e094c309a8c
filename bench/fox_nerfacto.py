"""sp-nerfacto vs its baseline (``--pipeline.model.sp.enabled False``) on the real fox capture, at the
CPU recipe: paired in one process (same seed, same rays per step, steps alternating), test-view
PSNR / SSIM and seconds per step.

    python -m bench.fox_nerfacto --steps 1500          # writes bench/out/fox_nerfacto.json
    python -m bench.fox_nerfacto --data PATH/TO/fox   # the capture (default: SP_FOX_CAPTURE, or ../shared/data/real/fox)

The recipe is the package's ``nerfacto-cpu`` (:mod:`sp_plugins.nerfstudio.recipes`), which the README
gives as ``ns-train`` flags (``python -m sp_plugins.nerfstudio.recipes nerfacto-cpu``; ``--print-flags``
here prints the same).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path
from typing import List

from bench.harness import nerfstudio as ns
from bench.harness.common import OUT_DIR, machine_info, start, write_json
from bench.harness.scenes import FOX, capture
from sp_plugins.nerfstudio.recipes import RECIPES

RECIPE = RECIPES["nerfacto-cpu"].flags
"""CPU recipe for sp-nerfacto on a real capture (the rest are nerfacto's settings)."""


def recipe_flags() -> List[str]:
    return RECIPES["nerfacto-cpu"].argv()


def fox_config(sp: bool, steps: int, out: Path, data: Path):
    from nerfstudio.data.dataparsers.instant_ngp_dataparser import InstantNGPDataParserConfig

    from sp_plugins.adapter.shrink import shrink
    from sp_plugins.nerfstudio.runs import configure_run, method_config

    config = method_config("sp-nerfacto")
    configure_run(config, data, steps=steps, output_dir=out, experiment_name=f"fox-{'sp' if sp else 'baseline'}")
    dm = config.pipeline.datamanager
    dm.dataparser = InstantNGPDataParserConfig(data=data)
    dm.train_num_rays_per_batch = RECIPE["pipeline.datamanager.train-num-rays-per-batch"]
    shrink(config, **{key.rpartition(".")[2].replace("-", "_"): value for key, value in RECIPE.items() if key.startswith("pipeline.model.")},
           sp=dataclasses.replace(config.pipeline.model.sp, enabled=sp))
    config.mixed_precision = False  # no AMP on a CPU
    return config


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", type=Path, default=FOX, help="the fox capture (instant-ngp format; default %(default)s)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--print-flags", action="store_true", help="print the recipe as ns-train flags and exit")
    args = parser.parse_args(argv)
    if args.print_flags:
        print(" ".join(recipe_flags()))
        return
    data = capture(args.data, hint="pass --data or set SP_FOX_CAPTURE")
    start(args.threads, quiet=())
    out = OUT_DIR / "fox_nerfacto_runs"
    runs = {name: ns.Run(name, fox_config(name == "sp", args.steps, out, data), args.seed) for name in ("baseline", "sp")}
    cpu = time.process_time()
    wall = ns.train_together(runs, args.steps, args.seed, "fox", log_every=max(1, args.steps // 10))
    cpu_per_step = (time.process_time() - cpu) / (2 * args.steps)  # one thread: CPU time is near idle wall time
    results = {}
    for name, run in runs.items():
        t0 = time.perf_counter()
        metrics = run.evaluate()
        seconds = time.perf_counter() - t0
        results[name] = {k: v for k, v in ns.run_summary(run, metrics).items() if k not in ("losses", "alphas")}
        results[name]["eval_s_per_image"] = seconds / len(metrics["psnr_per_view"])
        logging.info("%s: %s", name, results[name])
    payload = {
        "benchmark": "fox_nerfacto",
        "steps": args.steps,
        "seed": args.seed,
        "recipe_flags": recipe_flags(),
        "wall_s": wall,
        "cpu_s_per_step_both_runs": cpu_per_step,
        "machine": machine_info(),
        "results": results,
        "psnr_delta": results["sp"]["psnr"] - results["baseline"]["psnr"],
        "step_time_ratio": results["sp"]["median_step_s"] / results["baseline"]["median_step_s"],
    }
    path = write_json("fox_nerfacto", payload)
    b, s = results["baseline"], results["sp"]
    print(f"| fox, {args.steps} steps, seed {args.seed} | {b['psnr']:.2f} / {b['ssim']:.3f} | {s['psnr']:.2f} / {s['ssim']:.3f} "
          f"| {b['median_step_s']:.2f} / {s['median_step_s']:.2f} s |")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
