"""Point cloud -> SDF with a hash grid: baseline, geometric init, SP, both (the paper's Table 1).

For every mesh the four fits run side by side in ONE process, one step of each in turn, with
the same seed, batches and budget; they differ only in geometric initialisation and SP. Each is
meshed (marching cubes + bisection) and measured against the mesh it was sampled from, raw and
after keeping the largest component, with the Chamfer split into accuracy (reconstruction ->
truth: floaters, extra sheets) and completeness (truth -> reconstruction: the true surface), plus
F-score, normal consistency, the fraction of the volume with negative sign, and the area ratio.
Chamfer is also tracked against training steps (cheaper meshing), and SP's per-step cost is the
median ratio of paired step times.

Usage (resumable: a mesh whose result file exists is skipped)::

    python -m bench.pointcloud_sdf                       # all meshes, default budget
    python -m bench.pointcloud_sdf --meshes cow bunny --steps 3000 --tag long

Writes ``bench/out/pointcloud_sdf/<tag>/<mesh>.json`` per mesh and ``results.json``,
``results.md``, ``chamfer_vs_steps.png`` for the table.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path
from typing import Dict, List

import torch

from bench.harness.common import OUT_DIR, machine_info
from sp_plugins import SPConfig
from sp_plugins.geometry import load_oriented_points
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.pointcloud import PointCloudSDFConfig

MESH_DIR = Path(os.environ.get("SP_MESH_DIR", Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"))
MESHES = ("bunny", "cow", "fandisk", "homer", "spot")
CONFIGS = {  # name -> (geometric_init, sp)
    "baseline": (False, False),
    "geo-init": (True, False),
    "sp": (False, True),
    "sp+geo-init": (True, True),
}
SUMMARY_KEYS = (
    "chamfer", "accuracy", "completeness", "clean_chamfer", "clean_accuracy", "clean_completeness", "fscore",
    "clean_fscore", "normal_consistency", "negative_fraction", "area_ratio", "components",
)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--meshes", nargs="+", default=list(MESHES), help="mesh names in --mesh-dir (without .ply)")
    p.add_argument("--mesh-dir", type=Path, default=MESH_DIR)
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    p.add_argument("--tag", default="default", help="subfolder of the results (one per budget)")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=int, default=2500, help="surface points and uniform points per step (each)")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--lr-final-ratio", type=float, default=1.0)
    p.add_argument("--hidden", type=int, nargs="+", default=[64, 64])
    p.add_argument("--levels", type=int, default=16)
    p.add_argument("--log2-table", type=int, default=16)
    p.add_argument("--max-res", type=int, default=1024)
    p.add_argument("--include-input", choices=["auto", "yes", "no"], default="auto",
                   help="coordinates as MLP input: auto = only with geometric init (the paper's code)")
    p.add_argument("--output-bias", type=float, default=None, help="initial MLP output bias (None: PyTorch default)")
    p.add_argument("--eikonal", choices=["squared", "abs"], default="squared")
    p.add_argument("--alpha0", type=float, default=0.02)
    p.add_argument("--schedule", default="step", choices=["constant", "step", "exponential", "linear"])
    p.add_argument("--end", type=float, default=0.2, help="SP ends at this fraction of training (or step if > 1)")
    p.add_argument("--evals", type=int, default=8, help="cheap Chamfer checkpoints along training")
    p.add_argument("--eval-resolution", type=int, default=96)
    p.add_argument("--eval-points", type=int, default=30_000)
    p.add_argument("--mesh-resolution", type=int, default=192)
    p.add_argument("--metric-points", type=int, default=200_000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--keep-meshes", action="store_true", help="also write each final mesh (PLY, in the frame)")
    p.add_argument("--summarize-only", action="store_true", help="only rebuild the table from existing results")
    p.add_argument("--soundness-seeds", type=int, nargs="+", default=None,
                   help="instead of the table: for each seed, run --configs for --steps and record whether the "
                        "field came out sound (one sheet, positive outside); cheap, use a few hundred steps")
    return p.parse_args(argv)


def make_config(args, geometric_init: bool, sp_on: bool) -> PointCloudSDFConfig:
    include = {"auto": None, "yes": True, "no": False}[args.include_input]
    return PointCloudSDFConfig(
        steps=args.steps, seed=args.seed, surface_batch=args.batch, space_batch=args.batch, lr=args.lr,
        lr_final_ratio=args.lr_final_ratio, hidden=tuple(args.hidden), geometric_init=geometric_init,
        include_input=include, output_bias=args.output_bias, eikonal=args.eikonal,
        mesh_resolution=args.mesh_resolution, metric_points=args.metric_points,
        encoding=EncodingConfig(kind="hashgrid", levels=args.levels, log2_table_size=args.log2_table, max_resolution=args.max_res),
        sp=SPConfig(enabled=sp_on, alpha0=args.alpha0, schedule=args.schedule, end=args.end),
    )


def run_mesh(args, name: str, out_dir: Path) -> dict:
    data = load_oriented_points(args.mesh_dir / f"{name}.ply", n_points=200_000, seed=args.seed)
    trainers = {c: make_config(args, *CONFIGS[c]).setup(data) for c in args.configs}
    checkpoints = sorted({max(1, round(args.steps * (i + 1) / args.evals)) for i in range(args.evals)}) if args.evals else []
    curves: Dict[str, List[dict]] = {c: [] for c in trainers}
    start = time.time()
    names = list(trainers)
    for step in range(1, args.steps + 1):
        for c in (names if step % 2 else names[::-1]):  # alternate the order: load hits all alike
            trainers[c].step()
        if step in checkpoints and step != args.steps:
            for c, t in trainers.items():
                _, m = t.evaluate(data.mesh, resolution=args.eval_resolution, refine=2, metric_points=args.eval_points)
                curves[c].append({k: m[k] for k in ("step", "chamfer", "clean_chamfer", "accuracy", "completeness", "negative_fraction")})
            print(f"  {name} step {step}: " + "  ".join(f"{c} {curves[c][-1]['chamfer']:.4f}" for c in trainers), flush=True)
    train_seconds = time.time() - start
    result = {"mesh": name, "train_seconds": train_seconds, "configs": {}}
    for c, t in trainers.items():
        mesh, final = t.evaluate(data.mesh)
        cheap = t.evaluate(data.mesh, resolution=args.eval_resolution, refine=2, metric_points=args.eval_points)[1]
        curves[c].append({k: cheap[k] for k in ("step", "chamfer", "clean_chamfer", "accuracy", "completeness", "negative_fraction")})
        if args.keep_meshes:
            mesh.export(out_dir / f"{name}_{c}.ply")
        result["configs"][c] = {
            "final": final, "curve": curves[c], "step_seconds": t.timer.times,
            "final_loss": statistics.fmean(t.history["loss"][-50:]),
        }
    result["eval_seconds"] = time.time() - start - train_seconds
    return result


def true_negative_fraction(data, resolution: int = 48) -> float:
    """Share of the [-1, 1]^3 frame inside the true mesh: ray containment when it is watertight,
    else the side of the nearest oriented surface sample (bunny and spot have holes)."""
    import numpy as np
    from scipy.spatial import cKDTree

    from sp_plugins.geometry import Frame, sample_surface

    frame = Frame.fit(np.asarray(data.mesh.vertices), 1.9)
    mesh = frame.mesh_to_frame(data.mesh)
    axis = np.linspace(-1.0, 1.0, resolution)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    if data.mesh.is_watertight:
        return float(mesh.contains(grid).mean())
    pts, nrm = sample_surface(mesh, 200_000, seed=0)
    _, idx = cKDTree(pts).query(grid, workers=1)
    return float((np.sum((grid - pts[idx]) * nrm[idx], axis=1) < 0).mean())


def is_sound(result: dict, true_negative: float) -> bool:
    """One sheet (0.75 < area ratio < 1.3) and the negative share within a factor 1.5 of the
    true interior's (a field positive or negative nearly everywhere fails)."""
    ratio = result["negative_fraction"] / true_negative
    return bool(0.75 < result["area_ratio"] < 1.3 and 1 / 1.5 < ratio < 1.5)


def field_soundness(trainer, true_area: float, true_negative: float, resolution: int = 64) -> dict:
    """Sign and sheet count of a fitted field, from a coarse grid: the negative share of the
    volume and the reconstructed / true area (see :func:`is_sound`)."""
    from sp_plugins.geometry import evaluate_grid, mesh_from_grid

    with torch.no_grad():
        volume = evaluate_grid(trainer.sdf, (-1.0, 1.0), resolution)
    mesh = mesh_from_grid(volume, (-1.0, 1.0))
    ratio = float(mesh.area / (true_area * trainer.frame.scale**2)) if len(mesh.faces) else 0.0
    out = {"negative_fraction": float((volume < 0).mean()), "area_ratio": ratio}
    return dict(out, sound=is_sound(out, true_negative))


def run_soundness(args, name: str) -> dict:
    data = load_oriented_points(args.mesh_dir / f"{name}.ply", n_points=200_000, seed=0)
    true_negative = true_negative_fraction(data)
    out = {"mesh": name, "seeds": {}, "true_negative_fraction": true_negative}
    start = time.time()
    for seed in args.soundness_seeds:
        seeded = argparse.Namespace(**{**vars(args), "seed": seed})
        trainers = {c: make_config(seeded, *CONFIGS[c]).setup(data) for c in args.configs}
        for step in range(args.steps):
            for t in trainers.values():
                t.step()
        out["seeds"][seed] = {c: field_soundness(t, data.mesh.area, true_negative) for c, t in trainers.items()}
        print(f"  {name} seed {seed}: " + "  ".join(
            f"{c} {'sound' if r['sound'] else 'UNSOUND'} (neg {r['negative_fraction']:.3f}, area x{r['area_ratio']:.2f})"
            for c, r in out["seeds"][seed].items()), flush=True)
    out["seconds"] = time.time() - start
    return out


def summarize_soundness(args, out_dir: Path) -> None:
    results = {n: json.loads((out_dir / f"soundness_{n}.json").read_text()) for n in args.meshes
               if (out_dir / f"soundness_{n}.json").exists()}
    if not results:
        return
    lines = [f"Soundness `{out_dir.name}`: {json.loads((out_dir / 'settings.json').read_text())['command']}", "",
             "| mesh | true negative share | " + " | ".join(f"{c} sound" for c in args.configs) + " |",
             "|---|---|" + "---|" * len(args.configs)]
    totals = {c: [0, 0] for c in args.configs}
    for name, r in results.items():
        if "true_negative_fraction" not in r:  # files from before the truth was recorded
            r["true_negative_fraction"] = true_negative_fraction(
                load_oriented_points(args.mesh_dir / f"{name}.ply", n_points=1000, seed=0))
        cells = []
        for c in args.configs:
            flags = [is_sound(s[c], r["true_negative_fraction"]) for s in r["seeds"].values() if c in s]
            totals[c][0] += sum(flags)
            totals[c][1] += len(flags)
            cells.append(f"{sum(flags)}/{len(flags)}")
        lines.append(f"| {name} | {r['true_negative_fraction']:.3f} | " + " | ".join(cells) + " |")
    lines.append("| all | | " + " | ".join(f"{a}/{b}" for a, b in totals.values()) + " |")
    total = sum(r["seconds"] for r in results.values())
    lines.append(f"\nWall time: {total / 60:.1f} min.")
    (out_dir / "soundness.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def step_ratio(a: List[float], b: List[float]) -> float:
    """Median of paired per-step time ratios (the first 5 steps are warm-up)."""
    return statistics.median(x / y for x, y in zip(a[5:], b[5:]))


def summarize(args, out_dir: Path) -> None:
    results = {}
    for name in args.meshes:
        path = out_dir / f"{name}.json"
        if path.exists():
            results[name] = json.loads(path.read_text())
    if not results:
        print("no results yet")
        return
    configs = [c for c in CONFIGS if all(c in r["configs"] for r in results.values())]
    lines = [f"Budget `{out_dir.name}`: {json.loads((out_dir / 'settings.json').read_text())['command']}", ""]

    floors = sampling_floors(args, list(results))

    def table(key: str, title: str, fmt: str = "{:.5f}", floor: bool = False) -> None:
        extra = " truth vs itself |" if floor else ""
        lines.extend([f"**{title}**", "", "| mesh | " + " | ".join(configs) + " | sp / baseline | sp+geo / geo |" + extra,
                      "|---|" + "---|" * (len(configs) + 2 + int(floor))])
        for name, r in results.items():
            vals = {c: r["configs"][c]["final"][key] for c in configs}
            ratio = lambda a, b: f"{vals[a] / vals[b]:.2f}" if a in vals and b in vals and vals[b] else "-"  # noqa: E731
            lines.append(f"| {name} | " + " | ".join(fmt.format(vals[c]) for c in configs)
                         + f" | {ratio('sp', 'baseline')} | {ratio('sp+geo-init', 'geo-init')} |"
                         + (f" {floors[name]:.5f} |" if floor else ""))
        lines.append("")

    table("chamfer", "Chamfer (mean of both directions, / GT bbox diagonal; the last column is the sampling floor)", floor=True)
    table("clean_chamfer", "Chamfer after keeping the largest component", floor=True)
    table("accuracy", "Accuracy: reconstruction -> truth (floaters, extra sheets)")
    table("completeness", "Completeness: truth -> reconstruction (the true surface)")
    table("fscore", "F-score at 1% of the diagonal", "{:.3f}")
    table("normal_consistency", "Normal consistency", "{:.3f}")
    table("negative_fraction", "Fraction of the volume with negative sign (sound: the object's share, a few %)", "{:.3f}")
    table("area_ratio", "Reconstructed / true area (2 = a second sheet)", "{:.2f}")
    timing = []
    for name, r in results.items():
        cs = r["configs"]
        if "sp" in cs and "baseline" in cs:
            timing.append(step_ratio(cs["sp"]["step_seconds"], cs["baseline"]["step_seconds"]))
        if "sp+geo-init" in cs and "geo-init" in cs:
            timing.append(step_ratio(cs["sp+geo-init"]["step_seconds"], cs["geo-init"]["step_seconds"]))
    if timing:
        lines.append(f"SP per-step time / baseline (median of paired steps, per mesh and init): "
                     f"{', '.join(f'{t:.3f}' for t in timing)}")
    total = sum(r["train_seconds"] + r["eval_seconds"] for r in results.values())
    lines.append(f"Wall time: {total / 60:.1f} min for {len(results)} meshes x {len(configs)} configurations "
                 f"({statistics.fmean(statistics.fmean(r['configs'][c]['step_seconds']) for r in results.values() for c in configs):.3f} s per step on average).")
    (out_dir / "results.md").write_text("\n".join(lines) + "\n")
    (out_dir / "results.json").write_text(json.dumps(
        {n: {c: {k: r["configs"][c]["final"][k] for k in SUMMARY_KEYS} for c in configs} for n, r in results.items()}, indent=2))
    plot_curves(results, configs, out_dir / "chamfer_vs_steps.png")
    print("\n".join(lines))


def sampling_floors(args, names: List[str]) -> Dict[str, float]:
    """Chamfer of each true mesh against itself (two independent samplings of --metric-points):
    the lowest value any reconstruction can reach here."""
    from sp_plugins.geometry import load_mesh, mesh_metrics

    return {n: mesh_metrics(load_mesh(args.mesh_dir / f"{n}.ply"), load_mesh(args.mesh_dir / f"{n}.ply"),
                            n_points=args.metric_points)["chamfer"] for n in names}


def plot_curves(results: dict, configs: List[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(3.2 * len(results), 3.2), squeeze=False)
    for ax, (name, r) in zip(axes[0], results.items()):
        for c in configs:
            curve = r["configs"][c]["curve"]
            ax.plot([p["step"] for p in curve], [p["chamfer"] for p in curve], marker="o", ms=3, label=c)
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("Chamfer (96^3 meshing, 30k points)")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    out_dir = OUT_DIR / "pointcloud_sdf" / args.tag
    out_dir.mkdir(parents=True, exist_ok=True)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    settings_path = out_dir / "settings.json"
    budget_keys = [k for k in settings if k not in ("meshes", "summarize_only", "keep_meshes", "threads", "mesh_dir")]
    if settings_path.exists():
        old = json.loads(settings_path.read_text())
        changed = [k for k in budget_keys if old.get("args", {}).get(k) != settings[k]]
        if changed and not args.summarize_only:
            raise SystemExit(f"--tag {args.tag}: results there used other settings ({', '.join(changed)}); "
                             "use another --tag or delete the folder")
    else:
        command = "python -m bench.pointcloud_sdf " + " ".join(
            f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
            for k, v in settings.items() if k in budget_keys and v is not None)
        settings_path.write_text(json.dumps({"args": settings, "command": command, "machine": machine_info()}, indent=2))
    if args.soundness_seeds is not None:
        for name in args.meshes:
            path = out_dir / f"soundness_{name}.json"
            if path.exists() or args.summarize_only:
                continue
            print(f"{name}: soundness over seeds {args.soundness_seeds}", flush=True)
            path.write_text(json.dumps(dict(run_soundness(args, name), machine=machine_info())))
        summarize_soundness(args, out_dir)
        return
    if not args.summarize_only:
        for name in args.meshes:
            path = out_dir / f"{name}.json"
            if path.exists():
                print(f"{name}: done already ({path}), skipped")
                continue
            print(f"{name}: {len(args.configs)} fits x {args.steps} steps, interleaved", flush=True)
            result = run_mesh(args, name, out_dir)
            result["machine"] = machine_info()
            path.write_text(json.dumps(result, default=float))
            for c, r in result["configs"].items():
                f = r["final"]
                print(f"  {c:12s} chamfer {f['chamfer']:.5f} clean {f['clean_chamfer']:.5f} acc {f['accuracy']:.5f} "
                      f"comp {f['completeness']:.5f} F {f['fscore']:.3f} neg {f['negative_fraction']:.3f}", flush=True)
    summarize(args, out_dir)


if __name__ == "__main__":
    main()
