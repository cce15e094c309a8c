"""The paper's robustness study at CPU scale: how often does a hyperparameter setting succeed,
with and without SP? Two sweeps, both run by ``sp-sweep`` (Ray Tune, resumable):

- ``neus``: NeuS-hashgrid vs SP-NeuS-hashgrid (``--pipeline.model.sp.enabled``) on the bundled
  Spot scene (``sp-scene spot``, 24 views of 64x64, 4 test views), over network lr, hash-grid lr
  (``--optimizers.field-grid``), max resolution (to 2048) and log2 table size (to 19); test PSNR
  from ``ns-eval``.
- ``pointcloud``: ``sp-fit pointcloud`` on Spot (hash grid, no geometric init) over lr, log2 table
  size, max resolution and SP's alpha0 (an SP-only axis: one baseline per other setting); success
  is a *sound* field (one sheet, right sign) and the F-score.

The full grids are 3^4 = 81 points per study, more than this shared 2-core CPU runs in the time
we had: ``--sample N`` runs N grid points drawn at random, in random order, so a study stopped
early still covers the grid evenly. Rerunning the same command resumes (finished trials are
skipped); a larger ``--sample`` (same seed) adds points.

Usage::

    python -m bench.robustness_studies neus --sample 12          # 24 trials
    python -m bench.robustness_studies pointcloud --sample 16
    python -m bench.robustness_studies neus --sample 12 --summarize-only --success "psnr >= 24"

Output: ``bench/out/robustness/<study>/`` (``results.md``, ``results.csv``, ``histogram.png``,
one folder per trial).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from bench.harness.common import OUT_DIR

ROOT = OUT_DIR / "robustness"
SPOT = Path(__file__).resolve().parents[1] / "sp_plugins" / "data" / "assets" / "spot.ply"

NEUS_STEPS = 200
NEUS_FIXED = (
    f"--max-num-iterations {NEUS_STEPS} --steps-per-save {NEUS_STEPS} --steps-per-eval-batch 1000000 "
    "--steps-per-eval-image 1000000 --steps-per-eval-all-images 1000000 --logging.local-writer.enable False "
    "--pipeline.datamanager.train-num-rays-per-batch 256 --pipeline.datamanager.eval-num-rays-per-batch 256 "
    "--pipeline.model.num-samples 32 --pipeline.model.num-samples-importance 16 --pipeline.model.num-up-sample-steps 2 "
    "--pipeline.model.background-model none --pipeline.model.background-color white "
    "--pipeline.model.eval-num-rays-per-chunk 1024 --pipeline.model.sdf-field.hidden-dim 64 "
    "--pipeline.model.sdf-field.hidden-dim-color 64 --pipeline.model.sdf-field.geo-feat-dim 31 "
    "--pipeline.model.sdf-field.bias 0.5 "
    + " ".join(f"--optimizers.{g}.scheduler.warm-up-end 50 --optimizers.{g}.scheduler.max-steps {NEUS_STEPS}"
               for g in ("fields", "field-grid", "field-background"))
)

STUDIES = {
    "neus": {
        "command": f"ns-train neus-hashgrid {NEUS_FIXED}",
        "data": "blender-data --data {scene}/blender",
        "grid": {
            "optimizers.fields.optimizer.lr": ["1e-3", "5e-3", "2e-2"],
            "optimizers.field-grid.optimizer.lr": ["1e-3", "5e-3", "2e-2"],
            "pipeline.model.sdf-field.max-res": ["256", "1024", "2048"],
            "pipeline.model.sdf-field.log2-hashmap-size": ["14", "17", "19"],
        },
        "metric": "psnr",
    },
    "pointcloud": {
        "command": f"sp-fit pointcloud {SPOT} --steps 300 --mesh-resolution 128 --metric-points 50000 "
                   "--sp.schedule step --sp.end 200",
        "grid": {
            "lr": ["3e-4", "1e-3", "3e-3"],
            "encoding.log2-table-size": ["14", "16", "19"],
            "encoding.max-resolution": ["256", "1024", "2048"],
            "sp.alpha0": ["0.01", "0.03", "0.06"],
        },
        "sp_only": ["sp.alpha0"],
        "success": ["sound == 1"],
        "metric": "fscore",
    },
}


def write_spec(study: str, sample: int, sample_seed: int, success) -> Path:
    out = ROOT / study
    out.mkdir(parents=True, exist_ok=True)
    spec = dict(STUDIES[study])
    if "data" in spec:
        scene = ROOT / "spot"
        if not (scene / "scene.json").is_file():
            subprocess.run([str(Path(sys.executable).parent / "sp-scene"), "spot", str(scene), "--views", "24",
                            "--val-views", "2", "--test-views", "4", "--resolution", "64", "--layouts", "blender",
                            "--quiet"], check=True)
        spec["data"] = spec["data"].format(scene=scene)
    spec.update(sample=sample, sample_seed=sample_seed)
    if success:
        spec["success"] = list(success)
    path = out / "study.json"
    path.write_text(json.dumps(spec, indent=1) + "\n")
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("study", choices=sorted(STUDIES))
    p.add_argument("--sample", type=int, default=12, help="grid points to run (of 81), in a seeded random order")
    p.add_argument("--sample-seed", type=int, default=0)
    p.add_argument("--success", nargs="+", default=None, help="success criteria (default: the study's)")
    p.add_argument("--num-cpus", type=int, default=1, help="local Ray CPUs (trials run 1 CPU each)")
    p.add_argument("--summarize-only", action="store_true")
    p.add_argument("--publish", action="store_true",
                   help="copy results.md / .csv to bench/results/ and the histogram to docs/ (the committed copies)")
    args = p.parse_args(argv)
    spec = write_spec(args.study, args.sample, args.sample_seed, args.success)
    cmd = [str(Path(sys.executable).parent / "sp-sweep"), str(spec), "--out", str(ROOT / args.study),
           "--num-cpus", str(args.num_cpus), "--cpus-per-trial", "1"]
    if args.summarize_only or args.publish:
        cmd.append("--summarize-only")
    code = subprocess.run(cmd).returncode
    if args.publish and code == 0:
        import shutil

        repo = Path(__file__).resolve().parents[1]
        (repo / "bench" / "results").mkdir(exist_ok=True)
        src = ROOT / args.study
        shutil.copy(src / "results.csv", repo / "bench" / "results" / f"robustness_{args.study}.csv")
        text = (src / "results.md").read_text().replace("](histogram.png)", f"](../../docs/robustness_{args.study}.png)")
        (repo / "bench" / "results" / f"robustness_{args.study}.md").write_text(text)
        if (src / "histogram.png").is_file():
            shutil.copy(src / "histogram.png", repo / "docs" / f"robustness_{args.study}.png")
    return code


if __name__ == "__main__":
    sys.exit(main())
