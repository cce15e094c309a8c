"""Baseline vs SP in a nerfbaselines results table, at a CPU budget.

Four runs of ``nerfbaselines train --backend python`` on the bundled Spot scene (sp-scene, Blender
layout through nerfbaselines' own loader): ``nerfacto+sp-off`` against ``nerfacto+sp`` (nerfbaselines'
nerfacto config through ``with_sp``, SP off and on, with nerfbaselines' ``blender`` preset;
nerfbaselines' own ``nerfacto`` takes ``--set`` values as strings, so it cannot be shrunk to a CPU
budget), and ``mipnerf`` (nerfstudio's, which nerfbaselines lacks) against ``mipnerf+sp``; then
nerfbaselines' ``generate-dataset-results`` makes the table from the results JSON the runs wrote.
LPIPS: no backbone weights here, so the column is NaN (the runs say so in one line).

    python -m bench.nerfbaselines_table [--steps 300] [--out bench/out/nerfbaselines]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent
COMMON = ["--set", "machine.device_type=cpu", "--set", "pipeline.model.eval_num_rays_per_chunk=1024"]
RUNS = {
    "nerfacto": ["--presets", "blender", "--set", "pipeline.datamanager.train_num_rays_per_batch=256",
                 "--set", "pipeline.model.log2_hashmap_size=14", "--set", "pipeline.model.max_res=128",
                 "--set", "pipeline.model.num_nerf_samples_per_ray=16",
                 "--set", "pipeline.model.num_proposal_samples_per_ray=32,16", "--set", "pipeline.model.hidden_dim=32"],
    "mipnerf": ["--set", "pipeline.datamanager.train_num_rays_per_batch=128",
                "--set", "pipeline.model.num_coarse_samples=24", "--set", "pipeline.model.num_importance_samples=24"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--out", type=Path, default=Path("bench/out/nerfbaselines"))
    parser.add_argument("--table", type=Path, default=Path("bench/results/nerfbaselines/table.md"))
    args = parser.parse_args()
    env = dict(os.environ, OMP_NUM_THREADS="1")
    scene = args.out / "spot"
    if not (scene / "blender" / "nb-info.json").exists():
        subprocess.run([str(BIN / "sp-scene"), "spot", str(scene), "--overwrite", "--quiet"], env=env, check=True)
    for base, flags in RUNS.items():
        for method in (base + "+sp-off" if base == "nerfacto" else base, base + "+sp"):
            out = args.out / "results" / method / "spot"
            if (out / f"results-{args.steps}.json").exists():
                continue
            shutil.rmtree(out, ignore_errors=True)
            start = time.time()
            subprocess.run([str(BIN / "nerfbaselines"), "train", "--method", method, "--backend", "python",
                            "--data", str(scene / "blender"), "--output", str(out), "--set",
                            f"max_num_iterations={args.steps}", *COMMON, *flags], env=env, check=True)
            print(f"{method}: {time.time() - start:.0f} s", flush=True)
    args.table.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run([str(BIN / "nerfbaselines"), "generate-dataset-results", "--results", str(args.out / "results"),
                    "--dataset", "sp-scene", "--scenes", "spot", "--output", str(args.table)], env=env, check=True)
    print(args.table.read_text())


if __name__ == "__main__":
    main()
