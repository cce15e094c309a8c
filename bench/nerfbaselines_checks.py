"""nerfbaselines' own per-method checks (``nerfbaselines test-method``) on our specs: train,
eval-few, eval-all, render, save, reload without and with the dataset, re-save identical, render
after reload identical, a full Trainer run; exit 0 = all passed, 7 = some failed.

    python -m bench.nerfbaselines_checks [--steps 5] [--methods sp-nerfacto,...] [--out bench/out/nerfbaselines_checks]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent
METHODS = ("sp-nerfacto", "sp-mipnerf", "sp-vanilla-nerf", "sp-tensorf", "sp-relu-field", "sp-neus-hashgrid",
           "sp-neuralangelo-lite", "nerfacto+sp", "mipnerf", "vanilla-nerf")
BUDGET = ["--set", "machine.device_type=cpu", "--set", "pipeline.datamanager.train_num_rays_per_batch=64",
          "--set", "pipeline.model.eval_num_rays_per_chunk=1024"]
SIZES = {  # CPU-sized fields where the preset is GPU-sized
    "sp-neus-hashgrid": ["--set", "pipeline.model.num_samples=16", "--set", "pipeline.model.num_samples_importance=8",
                         "--set", "pipeline.model.num_up_sample_steps=1", "--set", "pipeline.model.num_samples_outside=8",
                         "--set", "pipeline.model.sdf_field.log2_hashmap_size=12"],
    "sp-relu-field": ["--set", "pipeline.model.resolution=33"],
}
SIZES["sp-neuralangelo-lite"] = SIZES["sp-neus-hashgrid"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--out", type=Path, default=Path("bench/out/nerfbaselines_checks"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    scene = args.out / "spot"
    env = dict(os.environ, OMP_NUM_THREADS="1", NERFBASELINES_NO_UPDATE_CHECK="1")
    if not (scene / "blender" / "nb-info.json").exists():
        subprocess.run([str(BIN / "sp-scene"), "spot", str(scene), "--resolution", "32", "--views", "8", "--test-views", "2",
                        "--overwrite", "--quiet"], env=env, check=True)
    report_path = args.out / "checks.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else {}
    for method in args.methods.split(","):
        data = scene / ("sdfstudio" if "neus" in method or "angelo" in method else "blender")
        start = time.time()
        proc = subprocess.run([str(BIN / "nerfbaselines"), "test-method", "--method", method, "--backend", "python",
                               "--data", str(data), "--steps", str(args.steps), *BUDGET, *SIZES.get(method, [])],
                              env=env, capture_output=True, text=True)
        text = re.sub(r"\x1b\[[0-9;]*m", "", proc.stdout + proc.stderr)
        marks = [line.strip() for line in text.splitlines() if line.strip()[:1] in ("\u2713", "\u26a0", "\u2717")]
        report[method] = {"rc": proc.returncode, "seconds": round(time.time() - start), "checks": marks,
                          "tail": text.splitlines()[-5:] if not marks else []}
        report_path.write_text(json.dumps(report, indent=1))
        print(method, proc.returncode, f"{len([m for m in marks if m[0] == chr(0x2713)])} passed", flush=True)


if __name__ == "__main__":
    main()
