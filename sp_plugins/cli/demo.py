"""``sp-demo``: baseline and SP trained side by side (on CUDA when available, else the CPU), on a bundled scene.

With no arguments it renders the bundled Spot mesh into a small multi-view scene (both dataset
layouts, for the nerfstudio methods), then fits a hash-grid SDF to the mesh's oriented point
cloud twice in one process, step for step: once plain, once with stochastic preconditioning.
That task is where SP's benefit shows at a CPU budget (``docs/results/pointcloud-sdf.md``). It ends with a
results table and the paths of the meshes, renders and convergence plot.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from sp_plugins.cli.threads import pick_threads

BUDGETS = {
    # steps, surface (and free-space) points per step, marching-cubes resolution
    "quick": (300, 1500, 128),
    "default": (2000, 2500, 192),
    "long": (4000, 5000, 256),
}
OUTPUTS = ("scene", "results.json", "results.md", "convergence.png", "renders.png", "slices.png", "meshes")


class UserInputError(Exception):
    """A problem with the arguments: reported as one line, not a traceback."""


def parse_args(argv: Optional[Sequence[str]]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="sp-demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", default="spot", help="a mesh file, or 'spot' (bundled) / a primitive name (default: spot)")
    ap.add_argument("--out", default="sp-demo", help="output folder (default: ./sp-demo)")
    ap.add_argument("--budget", choices=sorted(BUDGETS), default="default", help="quick (300 steps, 1-2.5 min), default (2000 steps, 4-10 min on 2 idle cores), long (4000 steps)")
    ap.add_argument("--steps", type=int, default=None, help="override the budget's number of steps")
    ap.add_argument("--mesh-resolution", type=int, default=None,
                    help="marching-cubes grid of the final meshes (default: the budget's, 128 / 192 / 256)")
    ap.add_argument("--alpha0", type=float, default=0.03, help="SP's alpha in the [-1, 1] frame (default 0.03)")
    ap.add_argument("--sp-end", type=float, default=0.2, help="SP stops at this fraction of training (default 0.2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="auto", help="where to train: auto (CUDA when available, else the CPU), cpu, cuda, cuda:N or mps")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's own, capped at the cores other processes leave idle)")
    ap.add_argument("--overwrite", action="store_true", help="replace the results of an earlier demo in --out")
    return ap.parse_args(argv)


def _paired_configs(args: argparse.Namespace):
    from sp_plugins import SPConfig  # defers torch: --help and bad arguments answer at once
    from sp_plugins.tasks import EncodingConfig, PointCloudSDFConfig  # defers torch

    steps, batch, resolution = BUDGETS[args.budget]
    steps = steps if args.steps is None else args.steps
    if steps < 10:
        raise ValueError(f"--steps {steps}: use at least 10")
    resolution = resolution if args.mesh_resolution is None else args.mesh_resolution
    if resolution < 16:
        raise ValueError(f"--mesh-resolution {resolution}: use at least 16")
    # Hash grid without geometric initialisation and with a zero output bias: the setting in
    # which the paper reports plain hash grids failing and SP rescuing them.
    base = PointCloudSDFConfig(
        steps=steps,
        seed=args.seed,
        surface_batch=batch,
        space_batch=batch,
        output_bias=0.0,
        mesh_resolution=resolution,
        metric_points=100_000,
        encoding=EncodingConfig(kind="hashgrid", levels=16, log2_table_size=16, base_resolution=16, max_resolution=1024),
        sp=SPConfig(enabled=False),
    )
    sp = replace(base, sp=SPConfig(alpha0=args.alpha0, schedule="step", end=args.sp_end))
    return {"baseline": base, "SP": sp}


def _convergence_plot(curves: Dict[str, Dict[str, List[float]]], sp_end: int, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sp_plugins.tasks.common import smooth  # defers torch

    def finite(xs, ys):
        kept = [(x, y) for x, y in zip(xs, ys) if math.isfinite(y) and y > 0]
        return [x for x, _ in kept], [y for _, y in kept]

    fig, (ax_loss, ax_cd) = plt.subplots(1, 2, figsize=(11, 4))
    for name, c in curves.items():
        ax_loss.plot(smooth(c["loss"], 25), label=name, lw=1)
        ax_cd.plot(*finite(c["eval_step"], c["chamfer"]), "o-", label=f"{name}", ms=3)
        ax_cd.plot(*finite(c["eval_step"], c["clean_chamfer"]), "x--", label=f"{name}, largest component", ms=3, alpha=0.7)
    ax_loss.set_yscale("log")
    if any(finite(c["eval_step"], c["chamfer"])[1] for c in curves.values()):
        ax_cd.set_yscale("log")
    for ax in (ax_loss, ax_cd):
        ax.axvline(sp_end, color="gray", ls="--", lw=0.8)
        ax.text(sp_end, 1.0, " SP ends", transform=ax.get_xaxis_transform(), va="top", fontsize=8, color="gray")
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    ax_loss.set_ylabel("training loss (running mean)")
    ax_cd.set_ylabel("Chamfer distance / GT diagonal")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _render_grid(meshes: Dict[str, "object"], path: Path, size: int = 200) -> Path:
    """One row per mesh, three views from the lit side (the scene's light comes from above)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from sp_plugins.data.cameras import default_fov, intrinsics, look_at_origin  # defers trimesh
    from sp_plugins.data.render import LIGHT_DIRECTION, render_views  # defers trimesh

    light_azimuth = np.arctan2(LIGHT_DIRECTION[1], LIGHT_DIRECTION[0])
    azimuths = light_azimuth + np.radians([-70.0, 0.0, 70.0])
    elevation = np.radians(25.0)
    distance = 4.0
    positions = distance * np.stack(
        [np.cos(elevation) * np.cos(azimuths), np.cos(elevation) * np.sin(azimuths), np.full(3, np.sin(elevation))], -1
    )
    c2w = look_at_origin(positions)
    K = intrinsics(size, size, default_fov(0.85, distance))
    fig, axes = plt.subplots(len(meshes), len(c2w), figsize=(2.4 * len(c2w), 2.4 * len(meshes)), squeeze=False)
    for row, (name, mesh) in zip(axes, meshes.items()):
        if len(mesh.faces):
            rgba = render_views(mesh, c2w, K, size, size, supersample=2)
            rgb = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])  # on white
        else:
            rgb = np.ones((len(c2w), size, size, 3))
        for ax, image in zip(row, rgb):
            ax.imshow(np.clip(image, 0, 1))
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(name, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _slice_plot(trainers: Dict[str, "object"], gt_frame_mesh, path: Path, size: int = 256) -> Path:
    """The fitted SDFs on the cross-section through the object's centre (the plane of its two
    longest extents): sign as colour, the zero level in black, the true outline dashed. A second
    sheet or a field of the wrong sign is plain to see here, where a render only shows the outside."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import torch

    extent = gt_frame_mesh.extents
    normal_axis = int(np.argmin(extent))
    u_axis, v_axis = [a for a in range(3) if a != normal_axis]
    ticks = np.linspace(-1.0, 1.0, size)
    uu, vv = np.meshgrid(ticks, ticks)
    points = np.zeros((size * size, 3), dtype=np.float32)
    points[:, u_axis], points[:, v_axis] = uu.ravel(), vv.ravel()
    normal = np.eye(3)[normal_axis]
    outline = gt_frame_mesh.section(plane_origin=np.zeros(3), plane_normal=normal)
    fig, axes = plt.subplots(1, len(trainers), figsize=(4.2 * len(trainers), 4.2), squeeze=False)
    for ax, (name, trainer) in zip(axes[0], trainers.items()):
        with torch.no_grad():
            values = trainer.sdf(torch.from_numpy(points).to(trainer.device)).cpu().numpy().reshape(size, size)
        ax.imshow(values, extent=(-1, 1, -1, 1), origin="lower", cmap="RdBu_r", vmin=-0.25, vmax=0.25)
        if values.min() < 0 < values.max():
            ax.contour(uu, vv, values, levels=[0.0], colors="black", linewidths=1.2)
        if outline is not None:
            for line in outline.discrete:
                ax.plot(line[:, u_axis], line[:, v_axis], "--", color="limegreen", lw=1.0)
        inside = float((values < 0).mean())
        ax.set_title(f"{name}: negative on {inside:.0%} of the slice", fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    truth = ""
    if outline is not None:  # even-odd fill of the true outline's loops
        from matplotlib.path import Path as PolygonPath

        uv = np.stack([uu.ravel(), vv.ravel()], -1)
        inside_truth = np.zeros(len(uv), dtype=bool)
        for line in outline.discrete:
            inside_truth ^= PolygonPath(line[:, [u_axis, v_axis]]).contains_points(uv)
        truth = f"; truly inside: {inside_truth.mean():.0%} of the slice"
    fig.suptitle(f"SDF on a slice through the object (blue < 0 < red; black: zero level; dashed green: true surface{truth})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def run(args: argparse.Namespace) -> dict:
    import torch
    from tqdm.auto import tqdm

    from sp_plugins.data import load_mesh, make_scene  # defers trimesh: --help and bad arguments answer at once
    from sp_plugins.geometry import load_oriented_points, save_mesh  # defers trimesh
    from sp_plugins.tasks.common import prepare_output_dir, resolve_device  # defers torch

    # every argument is checked before --out is created, so a typo leaves nothing behind
    if args.threads is not None and args.threads < 1:
        raise UserInputError(f"--threads must be at least 1, got {args.threads}")
    try:
        device = resolve_device(args.device)
    except ValueError as err:
        raise UserInputError(str(err)) from None
    try:
        configs = _paired_configs(args)
    except ValueError as err:
        raise UserInputError(str(err)) from None
    try:
        source = load_mesh(args.mesh)
    except ValueError as err:
        raise UserInputError(f"--mesh {args.mesh}: {err}") from None
    try:
        out = prepare_output_dir(args.out, OUTPUTS, args.overwrite)
    except ValueError as err:
        raise UserInputError(str(err)) from None
    steps = configs["baseline"].steps
    t_start = time.perf_counter()

    print(f"[sp-demo] 1/4 rendering the {args.mesh!r} mesh into a multi-view scene in {out / 'scene'}")
    try:
        scene = make_scene(
            source, out / "scene", n_train=24, n_val=4, n_test=4, resolution=96, seed=args.seed, overwrite=args.overwrite, progress=True
        )
    except (ValueError, FileNotFoundError) as err:
        raise UserInputError(f"--mesh {args.mesh}: {err}") from None
    data = load_oriented_points(scene.gt_mesh, n_points=200_000, seed=args.seed)

    pick_threads(args.threads, prog="sp-demo")  # measured now, while this process is idle
    print(f"[sp-demo] 2/4 fitting a hash-grid SDF to its point cloud, baseline and SP side by side ({steps} steps each, on {device})")
    trainers = {name: cfg.setup(data, device=device) for name, cfg in configs.items()}
    curves = {name: {"loss": [], "eval_step": [], "chamfer": [], "clean_chamfer": []} for name in trainers}
    eval_every = steps // 6 if steps >= 60 else steps + 1  # a Chamfer curve only for real runs
    bar = tqdm(total=steps, desc="training", unit="step")
    for i in range(steps):
        records = {name: t.step() for name, t in trainers.items()}
        for name, r in records.items():
            curves[name]["loss"].append(r["loss"])
        bar.update(1)
        if (i + 1) % 25 == 0:
            bar.set_postfix(alpha=f"{records['SP']['alpha']:.3g}", **{f"loss_{n}": f"{r['loss']:.3g}" for n, r in records.items()})
        if (i + 1) % eval_every == 0 and i + 1 < steps:
            for name, t in trainers.items():
                _, m = t.evaluate(data.mesh, resolution=64, refine=0, metric_points=20_000)
                curves[name]["eval_step"].append(i + 1)
                curves[name]["chamfer"].append(m["chamfer"])
                curves[name]["clean_chamfer"].append(m["clean_chamfer"])
    bar.close()

    print("[sp-demo] 3/4 extracting meshes (marching cubes + bisection refinement) and measuring them")
    (out / "meshes").mkdir(exist_ok=True)
    metrics, meshes = {}, {}
    for name, t in trainers.items():
        mesh, m = t.evaluate(data.mesh)
        curves[name]["eval_step"].append(steps)
        curves[name]["chamfer"].append(m["chamfer"])
        curves[name]["clean_chamfer"].append(m["clean_chamfer"])
        mesh = t.frame.mesh_from_frame(mesh)
        meshes[name] = mesh
        save_mesh(mesh, out / "meshes" / f"{name.lower()}.ply")
        times = t.timer.times[5:] or t.timer.times
        metrics[name] = dict(m, seconds_per_step=sorted(times)[len(times) // 2])

    print("[sp-demo] 4/4 rendering the meshes and plotting convergence")
    renders = _render_grid({"ground truth": data.mesh, **meshes}, out / "renders.png")
    slices = _slice_plot(trainers, trainers["baseline"].frame.mesh_to_frame(data.mesh), out / "slices.png")
    plot = _convergence_plot(curves, int(round(args.sp_end * steps)), out / "convergence.png")

    rows = [
        ("Chamfer distance (lower is better)", "chamfer"),
        ("Chamfer, largest component", "clean_chamfer"),
        ("  reconstruction -> truth", "accuracy"),
        ("  truth -> reconstruction", "completeness"),
        ("F-score @1% of diagonal (higher is better)", "fscore"),
        ("normal consistency (higher is better)", "normal_consistency"),
        ("surface area / true area (2 = a second sheet)", "area_ratio"),
        ("surface components", "components"),
        ("seconds per step", "seconds_per_step"),
    ]
    table = ["| metric | baseline | SP | SP / baseline |", "|---|---|---|---|"]
    for label, key in rows:
        b, s = metrics["baseline"][key], metrics["SP"][key]
        ratio = f"{s / b:.2f}" if b else "-"
        table.append(f"| {label} | {b:.4g} | {s:.4g} | {ratio} |")
    table_md = "\n".join(table)
    elapsed = time.perf_counter() - t_start
    results = {
        "mesh": args.mesh,
        "steps": steps,
        "budget": args.budget,
        "sp": {"alpha0": args.alpha0, "schedule": "step", "end": args.sp_end},
        "metrics": metrics,
        "curves": curves,
        "seconds": elapsed,
        "threads": torch.get_num_threads(),
        "device": str(device),
    }
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(
        f"# sp-demo: point cloud -> SDF, hash grid, {steps} steps, seed {args.seed}\n\n{table_md}\n"
    )
    print()
    print(f"Point cloud -> SDF on {args.mesh!r}: hash grid (no geometric init), {steps} steps, "
          f"SP alpha {args.alpha0} for the first {args.sp_end:.0%} of training")
    print(table_md)
    print()
    print(f"meshes:      {out / 'meshes' / 'baseline.ply'}, {out / 'meshes' / 'sp.ply'} (ground truth: {scene.gt_mesh})")
    print(f"renders:     {renders}  (rows: ground truth, baseline, SP)")
    print(f"SDF slices:  {slices}  (sign of each field on a cross-section, true outline dashed)")
    print(f"convergence: {plot}")
    print(f"scene:       {scene.root}  (try: ns-train sp-neus-hashgrid ... blender-data --data {scene.blender})")
    print(f"results:     {out / 'results.json'}  ({elapsed / 60:.1f} min)")
    return results


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        run(args)
    except UserInputError as err:
        print(f"sp-demo: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
