"""The README's first SP examples, SP on and off, over seeds, as a user types them.

Each run is the README's command in a subprocess, with ``--machine.seed S`` and SP on or off, then the
README's evaluation of it. ``--example nerfacto``: ``sp-train nerfacto ... blender-data --data SCENE`` (off:
``--pipeline.model.sp.enabled False``), then ``ns-eval`` (test-view PSNR / SSIM). ``--example neus``: the NeuS
recipe, ``ns-train sp-neus-hashgrid`` against ``ns-train neus-hashgrid`` with the same flags, then
``sp-export-mesh`` at 256 and Chamfer / F-score against the scene's true mesh (``gt_mesh.ply``). nerfacto's two
settings of the same command:

- ``as-was``: the flags the README gave until 2026-12-06 (nerfacto's own settings for an unbounded real
  capture: contracted space, near 0.05 / far 1000, ``last_sample`` background, appearance embedding, camera
  optimizer, distortion loss) on the object-on-white ``sp-scene``;
- ``object``: the same plus the package's ``nerfacto-object`` recipe (``python -m
  sp_plugins.nerfstudio.recipes nerfacto-object``: nerfstudio's and nerfbaselines' settings for a Blender
  object scene: near 2 / far 6, white background, no contraction, no appearance embedding or camera
  optimizer, no distortion loss, a uniform initial proposal sampler).

    python -m bench.readme_examples                        # nerfacto: 3 seeds x SP on/off x both settings, 1000 steps
    python -m bench.readme_examples --example neus         # NeuS: 3 seeds x SP on/off, 400 steps, meshes
    python -m bench.readme_examples --settings object --seeds 0 --steps 300

Resumable: a run whose ``eval.json`` exists is read, not run again. Writes
``bench/out/readme_examples/<example>/results.json`` and ``results.md`` (the table ``docs/results/readme-examples-seeds.md`` quotes).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List

from bench.harness.common import OUT_DIR, machine_info

REPO = Path(__file__).resolve().parents[1]
"""Commands are recorded with paths from the repository root."""

BASE = ("--machine.device-type cpu --vis tensorboard --pipeline.datamanager.train-num-rays-per-batch 256 "
        "--pipeline.model.log2-hashmap-size 17 --pipeline.model.num-nerf-samples-per-ray 32 "
        "--pipeline.model.num-proposal-samples-per-ray 64 32")
"""The README's nerfacto flags (besides alpha0, steps and the recipe)."""
NEUS = ("--machine.device-type cpu --vis tensorboard --pipeline.datamanager.train-num-rays-per-batch 256 "
        "--pipeline.model.sdf-field.log2-hashmap-size 16 --pipeline.model.num-samples 32 "
        "--pipeline.model.num-samples-importance 16 --pipeline.model.num-samples-outside 16 "
        "--optimizers.fields.scheduler.warm-up-end 100 --optimizers.field-grid.scheduler.warm-up-end 100 "
        "--optimizers.field-background.scheduler.warm-up-end 100")
"""The README's NeuS flags (besides steps and SP's)."""
SETTINGS = {"nerfacto": ("as-was", "object"), "neus": ("as-written",)}
STEPS = {"nerfacto": 1000, "neus": 400}


def command(example: str, setting: str, sp: bool, seed: int, steps: int, out: Path, scene: Path) -> List[str]:
    from sp_plugins.nerfstudio.recipes import RECIPES

    tail = ["--output-dir", str(out), "--experiment-name", "run", "--timestamp", "run"]
    if example == "neus":
        argv = ["ns-train", "sp-neus-hashgrid" if sp else "neus-hashgrid", *shlex.split(NEUS), "--max-num-iterations", str(steps),
                "--machine.seed", str(seed)]
        if sp:
            argv += ["--pipeline.model.sp.alpha0", "0.013", "--pipeline.model.sp.end", "0.2"]
        return argv + tail + ["sdfstudio-data", "--data", str(scene / "sdfstudio")]
    argv = ["sp-train", "nerfacto", "--pipeline.model.sp.alpha0", "0.02", *shlex.split(BASE),
            "--max-num-iterations", str(steps), "--machine.seed", str(seed)]
    if setting == "object":
        argv += RECIPES["nerfacto-object"].argv()
    if not sp:
        argv += ["--pipeline.model.sp.enabled", "False"]
    return argv + tail + ["blender-data", "--data", str(scene / "blender")]


def _run(argv: List[str], name: str) -> float:
    t0 = time.monotonic()
    proc = subprocess.run(argv, env=dict(os.environ, OMP_NUM_THREADS="1"), capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{name}: {shlex.join(argv)} failed ({proc.returncode}):\n{(proc.stdout + proc.stderr)[-3000:]}")
    return time.monotonic() - t0


def evaluate(example: str, config: Path, out: Path, scene: Path, name: str) -> Dict:
    """nerfacto: ``ns-eval``'s test-view PSNR / SSIM; NeuS: ``sp-export-mesh`` at 256, then the mesh
    against the scene's true one (Chamfer and F-score in units of its bounding-box diagonal)."""
    if example == "nerfacto":
        evaluation = out / "ns-eval.json"
        seconds = _run(["ns-eval", "--load-config", str(config), "--output-path", str(evaluation)], name)
        metrics = json.loads(evaluation.read_text())["results"]
        return {"psnr": metrics["psnr"], "ssim": metrics["ssim"], "eval_s": round(seconds, 1)}
    import trimesh

    from sp_plugins.geometry.metrics import mesh_metrics

    seconds = _run(["sp-export-mesh", "--load-config", str(config), "--output-dir", str(out / "mesh"), "--resolution", "256"], name)
    mesh = trimesh.load(out / "mesh" / "mesh.ply", force="mesh")
    m = mesh_metrics(mesh, trimesh.load(scene / "gt_mesh.ply", force="mesh"))
    return {"chamfer": m["chamfer"], "fscore": m["fscore"], "normal_consistency": m["normal_consistency"],
            "area_ratio": m["area_ratio"], "eval_s": round(seconds, 1)}


def run_one(example: str, setting: str, sp: bool, seed: int, steps: int, root: Path, scene: Path) -> Dict:
    name = f"{setting}-{'sp' if sp else 'off'}-seed{seed}"
    out = root / "runs" / name
    result = out / "eval.json"
    if result.is_file():
        return json.loads(result.read_text())
    if out.exists():  # an interrupted run: start it again
        shutil.rmtree(out)
    argv = command(example, setting, sp, seed, steps, out, scene)
    train_s = _run(argv, name)
    (config,) = out.glob("**/config.yml")
    record = {"name": name, "example": example, "setting": setting, "sp": sp, "seed": seed, "steps": steps,
              "command": shlex.join(argv).replace(f"{REPO}/", ""), "train_s": round(train_s, 1), **evaluate(example, config, out, scene, name)}
    result.write_text(json.dumps(record, indent=1))
    return record


METRICS = {"nerfacto": (("psnr", "test PSNR (dB)", 2), ("ssim", "SSIM", 3)),
           "neus": (("chamfer", "Chamfer (of the diagonal)", 4), ("fscore", "F-score @1%", 3), ("area_ratio", "area / true area", 2))}


def table(example: str, records: List[Dict]) -> str:
    metrics = METRICS[example]
    head = " | ".join(f"{label}, mean ± sd | per seed" for _, label, _ in metrics)
    lines = [f"| setting | SP | seeds | {head} | train time per run |", "|---|---|---:|" + "---|---|" * len(metrics) + "---:|"]
    for setting in SETTINGS[example]:
        for sp in (False, True):
            rows = sorted((r for r in records if r["setting"] == setting and r["sp"] == sp), key=lambda r: r["seed"])
            if not rows:
                continue
            cells = []
            for key, _, digits in metrics:
                values = [r[key] for r in rows]
                sd = statistics.stdev(values) if len(values) > 1 else 0.0
                cells.append(f"{statistics.mean(values):.{digits}f} ± {sd:.{digits}f} | {', '.join(f'{v:.{digits}f}' for v in values)}")
            lines.append(f"| {setting} | {'on' if sp else 'off'} | {len(rows)} | {' | '.join(cells)} | "
                         f"{statistics.mean(r['train_s'] for r in rows):.0f} s |")
    return "\n".join(lines + ["", differences(example, records)])


def differences(example: str, records: List[Dict]) -> str:
    """SP - baseline per metric, paired by seed, with its 95% t interval (what ``sp-compare`` reports)."""
    from sp_plugins.stats import paired_difference

    metrics = METRICS[example]
    lines = [f"| setting | pairs | {' | '.join(f'{label}: SP - baseline [95% t]' for _, label, _ in metrics)} |",
             "|---|---:|" + "---|" * len(metrics)]
    for setting in SETTINGS[example]:
        by_seed = {(r["seed"], r["sp"]): r for r in records if r["setting"] == setting}
        seeds = sorted(s for s, sp in by_seed if sp is False and (s, True) in by_seed)
        if not seeds:
            continue
        cells = []
        for key, _, digits in metrics:
            d = paired_difference([by_seed[(s, False)][key] for s in seeds], [by_seed[(s, True)][key] for s in seeds])
            cells.append(d.text(digits) + (f": {d.verdict}" if d.low is not None else " (one pair)"))
        lines.append(f"| {setting} | {len(seeds)} | {' | '.join(cells)} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--example", choices=sorted(SETTINGS), default="nerfacto")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, help="default: the README's budget (nerfacto 1000, NeuS 400)")
    parser.add_argument("--settings", nargs="+", help="nerfacto: as-was and/or object (default: both)")
    parser.add_argument("--out", type=Path, default=OUT_DIR / "readme_examples")
    args = parser.parse_args(argv)
    settings = args.settings or list(SETTINGS[args.example])
    unknown = sorted(set(settings) - set(SETTINGS[args.example]))
    if unknown:
        parser.error(f"--settings {' '.join(unknown)}: {args.example} has {', '.join(SETTINGS[args.example])}")
    steps = args.steps or STEPS[args.example]
    root = args.out / args.example
    scene = args.out / "my-scene"
    if not (scene / "blender").is_dir():
        subprocess.run(["sp-scene", "spot", str(scene)], check=True, capture_output=True)
    records = []
    for seed in args.seeds:  # seed-major: a stopped study has whole pairs
        for setting in settings:
            for sp in (False, True):
                record = run_one(args.example, setting, sp, seed, steps, root, scene)
                shown = ", ".join(f"{label} {record[key]:.{digits}f}" for key, label, digits in METRICS[args.example])
                print(f"{args.example} {record['name']}: {shown}, train {record['train_s']:.0f} s", flush=True)
                records.append(record)
    # the table holds every finished run of this example (earlier invocations' seeds and settings too)
    records = [json.loads(f.read_text()) for f in sorted((root / "runs").glob("*/eval.json"))]
    text = table(args.example, records)
    (root / "results.json").write_text(json.dumps({"machine": machine_info(), "runs": records}, indent=1))
    (root / "results.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    sys.exit(main())
