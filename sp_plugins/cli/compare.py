"""``sp-compare``: nerfstudio runs side by side, a method and its SP version on the same data, one pair or one per seed.

    sp-compare outputs/baseline/nerfacto/RUN outputs/sp/nerfacto/RUN --output-dir compare
    sp-compare --baseline A1 A2 A3 --sp B1 B2 B3 --output-dir compare      # paired by seed

With runs over seeds (``--baseline`` / ``--sp``, paired by ``--machine.seed``): each pair's report in
``seed-N/`` as below, then each side's mean and spread, the paired difference with its 95% t interval over the
seeds (:func:`sp_plugins.stats.paired_difference`) and a verdict in words (better, worse, within the noise), a
figure of every seed's values, and one page. One pair says plainly that it cannot tell SP's effect from
run-to-run noise.

Renders the same held-out views from both runs (the evaluation split nerfstudio's ``ns-eval`` scores), beside the
ground truth, with an error map per run on one colour scale; PSNR / SSIM (and LPIPS where its weights are cached)
per view and overall, as the model's own evaluation computes them; the training loss and PSNR of both runs from
their event files, with SP's alpha beside them; for SDF methods both meshes at one resolution, with Chamfer and
F-score against a true mesh when one is at hand (``--gt-mesh``, or the ``gt_mesh.ply`` an ``sp-scene`` folder
carries). Writes ``compare.html`` (one page, images inline, opens offline), ``compare.json`` and the PNGs, and
prints a one-screen table. Two runs on different data or with different held-out views are refused in one line. Where
the evaluation split is the training images (sdfstudio-data holds none out), the table, page and JSON say "training
views" instead of "held-out views".

Each run is opened as :mod:`sp_plugins.cli.run_folder` opens one (restricted ``config.yml`` loader,
weights-only checkpoint); nothing here changes a run folder.
"""

from __future__ import annotations

import argparse
import base64
import html
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from sp_plugins.adapter.checks import check_writable_dir
from sp_plugins.adapter.errors import InputError
from sp_plugins.cli.run_folder import Refused, answer, load_saved_config, model_sdf, setup_pipeline
from sp_plugins.patches import registry
from sp_plugins.stats import paired_difference, spread

PROG = "sp-compare"
CURVES = {"loss": "Train Loss", "psnr": "Train Metrics Dict/psnr", "alpha": "Train Metrics Dict/sp_alpha"}
"""Event-file tags nerfstudio's writer gives the training loss, the training PSNR and our models' ``sp_alpha``."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0].split(": ", 1)[1])
    parser.add_argument("run_a", type=Path, nargs="?", help="a run folder ns-train wrote (holding config.yml), or its config.yml")
    parser.add_argument("run_b", type=Path, nargs="?", help="the other run, on the same data")
    parser.add_argument("--baseline", type=Path, nargs="+", metavar="RUN", help="baseline runs, one per seed (with --sp; "
                        "instead of RUN_A RUN_B)")
    parser.add_argument("--sp", type=Path, nargs="+", metavar="RUN", help="the SP runs of the same seeds")
    parser.add_argument("--output-dir", type=Path, default=Path("compare"), help="where the report goes (default: ./compare)")
    parser.add_argument("--names", nargs=2, metavar=("A", "B"), help="labels of the runs (default: from their method, "
                        "experiment and SP setting)")
    parser.add_argument("--max-views", type=int, default=None, help="render at most this many held-out views (default: all)")
    parser.add_argument("--mesh-resolution", type=int, default=256, help="marching-cubes cells for SDF methods (default: 256)")
    parser.add_argument("--gt-mesh", type=Path, default=None, help="a true mesh in the scene's coordinates (default: the "
                        "gt_mesh.ply beside an sp-scene layout, if any)")
    return parser


@dataclass
class Run:
    label: str
    config_path: Path
    config: object
    pipeline: object = None
    step: int = 0
    views: List[dict] = field(default_factory=list)
    overall: Dict[str, float] = field(default_factory=dict)
    curves: Dict[str, List[List[float]]] = field(default_factory=dict)
    mesh: Optional[dict] = None


def config_of(path: Path) -> Path:
    if path.is_dir():
        found = sorted(path.glob("config.yml")) or sorted(path.glob("**/config.yml"))
        if len(found) != 1:
            raise Refused(f"{path}: {'no' if not found else len(found)} config.yml found in this folder; pass a run folder "
                          "that ns-train wrote (outputs/EXPERIMENT/METHOD/TIMESTAMP) or its config.yml")
        return found[0]
    return path


def data_of(config) -> Optional[Path]:
    dm = config.pipeline.datamanager
    data = getattr(dm, "data", None) or getattr(getattr(dm, "dataparser", None), "data", None)
    return Path(data).resolve() if data is not None else None


def sp_summary(config) -> str:
    sp = getattr(config.pipeline.model, "sp", None)
    if sp is None:
        return "no SP"
    return f"SP alpha0 {sp.alpha0:g} to 0 by {sp.end:g}" if sp.enabled else "SP off"


HELD_OUT = "held-out views"


def scored_kind(train: Sequence[str], scored: Sequence[str]) -> str:
    """What the scored views are to the runs: held out, or training views (a dataparser that holds out none, as
    sdfstudio-data: every split is every image), or held out in part."""
    seen = len(set(scored) & set(train))
    if seen == 0:
        return HELD_OUT
    return "training views" if seen == len(scored) else f"views ({seen} of them training views)"


def default_labels(a, b) -> List[str]:
    labels = []
    for config in (a, b):
        labels.append(f"{config.method_name} ({config.experiment_name}, {sp_summary(config)})")
    return labels if labels[0] != labels[1] else [f"A: {labels[0]}", f"B: {labels[1]}"]


# -- rendering and metrics ---------------------------------------------------------------------------
METRICS = ("psnr", "ssim", "lpips")


def image_metrics(metrics: Dict[str, float]) -> Dict[str, float]:
    """PSNR, SSIM and LPIPS from a model's own evaluation metrics: NeRF and MipNeRF name those of their fine
    network ``fine_ssim`` / ``fine_lpips`` (their ``psnr`` is the fine one too)."""
    found = {key: metrics.get(key, metrics.get(f"fine_{key}")) for key in METRICS}
    return {key: float(value) for key, value in found.items() if value is not None}


def render_views(run: Run, max_views: Optional[int]):
    """Per held-out view: the model's own evaluation metrics, the prediction and the ground truth (HxWx3 in [0, 1])."""
    import torch

    pipeline = run.pipeline
    model = pipeline.model
    model.eval()
    images = []
    with torch.no_grad():
        for index, (camera, batch) in enumerate(pipeline.datamanager.fixed_indices_eval_dataloader):
            if max_views is not None and index >= max_views:
                break
            outputs = model.get_outputs_for_camera(camera=camera)
            metrics, shown = model.get_image_metrics_and_images(outputs, batch)
            rgb = outputs["rgb_fine"] if "rgb_fine" in outputs else outputs["rgb"]
            width = rgb.shape[1]
            truth = shown["img"][:, :width, :3]
            run.views.append(image_metrics(metrics))
            images.append((rgb.clamp(0, 1).cpu().numpy(), truth.clamp(0, 1).cpu().numpy()))
    for key in METRICS:
        values = [v[key] for v in run.views if key in v and math.isfinite(v[key])]
        if values:
            run.overall[key] = sum(values) / len(values)
    return images


def read_curves(run: Run) -> None:
    """The loss, PSNR and SP alpha of training from the run's event files (none under ``--vis viewer`` alone)."""
    files = sorted(Path(run.config.get_base_dir()).glob("events.out.tfevents.*"))
    if not files:
        return
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    for file in files:
        events = EventAccumulator(str(file), size_guidance={"scalars": 0})
        events.Reload()
        tags = set(events.Tags().get("scalars", []))
        for key, tag in CURVES.items():
            if tag in tags:
                run.curves.setdefault(key, []).extend([e.step, e.value] for e in events.Scalars(tag))


def mesh_of(run: Run, resolution: int, gt) -> None:
    """The run's SDF meshed at ``resolution`` (None when the model has no SDF), with metrics against ``gt``."""
    import torch

    found = model_sdf(run.pipeline.model)
    if found is None:
        return
    from sp_plugins.geometry import mesh_metrics, sparse_extract_mesh  # defers torch, trimesh, scikit-image

    sdf, aabb, device = found
    with torch.no_grad():
        mesh = sparse_extract_mesh(sdf, (aabb[0], aabb[1]), resolution, device=device, progress=False)
    run.mesh = {"mesh": mesh, "vertices": len(mesh.vertices), "faces": len(mesh.faces)}
    if gt is not None and len(mesh.faces):
        m = mesh_metrics(mesh, gt)
        run.mesh.update({k: float(m[k]) for k in ("chamfer", "fscore", "normal_consistency", "area_ratio")})


# -- figures and report ----------------------------------------------------------------------------
def views_figure(images_a, images_b, runs: Sequence[Run], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = len(images_a)
    errors = [[np.abs(p - t).mean(-1) for p, t in images] for images in (images_a, images_b)]
    vmax = max(0.05, max(float(e.max()) for es in errors for e in es))
    fig, axes = plt.subplots(rows, 5, figsize=(12, 2.5 * rows + 0.4), squeeze=False)
    titles = ["ground truth", runs[0].label, runs[1].label, f"|error| {runs[0].label}", f"|error| {runs[1].label}"]
    for r in range(rows):
        (pa, truth), (pb, _) = images_a[r], images_b[r]
        panels = [truth, pa, pb, errors[0][r], errors[1][r]]
        for c, panel in enumerate(panels):
            ax = axes[r][c]
            ax.imshow(panel, cmap="magma" if c >= 3 else None, vmin=0, vmax=vmax if c >= 3 else None)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title("\n".join(_wrap(titles[c], 28)), fontsize=8)
        axes[r][0].set_ylabel(f"view {r}\n{runs[0].views[r].get('psnr', float('nan')):.2f} / "
                              f"{runs[1].views[r].get('psnr', float('nan')):.2f} dB", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _wrap(text: str, width: int) -> List[str]:
    import textwrap

    return textwrap.wrap(text, width) or [text]


def curves_figure(runs: Sequence[Run], path: Path) -> bool:
    """Both runs' loss and PSNR, SP's alpha dotted; a panel only where a run logged two steps or more of it
    (MipNeRF logs no training PSNR); False (no figure) when there is none."""
    panels = [(key, title) for key, title in (("loss", "training loss"), ("psnr", "training PSNR (dB)"))
              if any(len(run.curves.get(key, [])) > 1 for run in runs)]
    if not panels:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 3.6), squeeze=False)
    for ax, (key, title) in zip(axes[0], panels):
        for run, colour in zip(runs, ("tab:blue", "tab:orange")):
            points = sorted(run.curves.get(key, []))
            if points:
                ax.plot([p[0] for p in points], [p[1] for p in points], color=colour, label=run.label, lw=1,
                        marker="o" if len(points) < 20 else None, ms=3)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("step")
        if key == "loss":
            ax.set_yscale("log")
        alphas = [(run, sorted(run.curves.get("alpha", []))) for run in runs]
        if any(points for _, points in alphas):
            twin = ax.twinx()
            for (run, points), colour in zip(alphas, ("tab:blue", "tab:orange")):
                if points:
                    twin.plot([p[0] for p in points], [p[1] for p in points], color=colour, ls=":", lw=1)
            twin.set_ylabel("SP alpha (dotted)", fontsize=8)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def table(runs: Sequence[Run], kind: str = HELD_OUT) -> List[List[str]]:
    """Rows of the overall comparison: metric, run A, run B, B - A (or B / A for mesh distances)."""
    rows = [["", runs[0].label, runs[1].label, "B - A"]]
    for key, label in (("psnr", "PSNR (dB)"), ("ssim", "SSIM"), ("lpips", "LPIPS")):
        if key in runs[0].overall and key in runs[1].overall:
            a, b = runs[0].overall[key], runs[1].overall[key]
            rows.append([f"{label}, {len(runs[0].views)} {kind}", f"{a:.4g}", f"{b:.4g}", f"{b - a:+.3g}"])
    if runs[0].mesh and runs[1].mesh:
        for key, label in (("chamfer", "Chamfer (of the true diagonal)"), ("fscore", "F-score @1%"),
                           ("normal_consistency", "normal consistency"), ("area_ratio", "area / true area")):
            if key in runs[0].mesh and key in runs[1].mesh:
                a, b = runs[0].mesh[key], runs[1].mesh[key]
                rows.append([label, f"{a:.4g}", f"{b:.4g}", f"{b - a:+.3g}"])
    rows.append(["trained steps", str(runs[0].step), str(runs[1].step), ""])
    return rows


def _inline(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode()


def write_html(runs: Sequence[Run], rows: List[List[str]], figures: Dict[str, Path], notes: List[str], path: Path,
               kind: str = HELD_OUT) -> None:
    esc = html.escape
    head = "".join(f"<th>{esc(c)}</th>" for c in rows[0])
    body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in rows[1:])
    per_view = "".join(
        f"<tr><td>{i}</td>" + "".join(f"<td>{v.get(k, float('nan')):.4g}</td>" for v in (runs[0].views[i], runs[1].views[i])
                                      for k in ("psnr", "ssim")) + "</tr>" for i in range(len(runs[0].views)))
    images = "".join(f"<h2>{esc(title)}</h2><img alt=\"{esc(title)}\" src=\"{_inline(p)}\">" for title, p in figures.items())
    runs_list = "".join(f"<li><b>{esc(r.label)}</b>: <code>{esc(str(r.config_path))}</code>, step {r.step}, "
                        f"{esc(sp_summary(r.config))}</li>" for r in runs)
    text = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>sp-compare: {esc(runs[0].label)} vs {esc(runs[1].label)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:.3em .6em;text-align:right}}td:first-child,th:first-child{{text-align:left}}
img{{max-width:100%}}</style></head>
<body><h1>sp-compare</h1><ul>{runs_list}</ul>
<h2>Overall</h2><table><tr>{head}</tr>{body}</table>
{images}
<h2>Per view ({esc(kind)})</h2><table><tr><th>view</th><th>PSNR A</th><th>SSIM A</th><th>PSNR B</th><th>SSIM B</th></tr>{per_view}</table>
<p>{"<br>".join(esc(n) for n in notes)}</p>
</body></html>
"""
    path.write_text(text)


def print_table(rows: List[List[str]]) -> None:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for n, row in enumerate(rows):
        print("  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(row, widths))))
        if n == 0:
            print("  ".join("-" * w for w in widths))


# -- the command -----------------------------------------------------------------------------------
def main(argv: Optional[List[str]] = None) -> int:
    return answer(PROG, compare, build_parser().parse_args(argv))


ONE_PAIR_NOTE = ("One pair cannot tell SP's effect from run-to-run noise: over seeds 0-2 the README's examples moved by "
                 "1.6-2.3 dB in PSNR (nerfacto, sd) and 0.0006 in Chamfer (NeuS on a hash grid, sd). Train three seeds or "
                 "more a side (--machine.seed) and pass --baseline A1 A2 A3 --sp B1 B2 B3.")
"""What a one-pair comparison prints (the spreads: docs/results, "The README's first SP examples over seeds")."""


def check_options(args) -> None:
    if args.max_views is not None and args.max_views < 1:
        raise Refused(f"--max-views {args.max_views}: must be at least 1")
    if args.mesh_resolution < 16:
        raise Refused(f"--mesh-resolution {args.mesh_resolution}: need at least 16 cells (128 and up for a useful mesh)")
    seeded = args.baseline is not None or args.sp is not None
    if seeded and (args.run_a is not None or args.run_b is not None):
        raise Refused("pass either RUN_A RUN_B or --baseline ... --sp ..., not both")
    if seeded and (args.baseline is None or args.sp is None):
        raise Refused(f"--{'sp' if args.sp is None else 'baseline'} is missing: pass --baseline A1 A2 ... --sp B1 B2 ... "
                      "(runs of the same seeds)")
    if seeded and len(args.baseline) != len(args.sp):
        raise Refused(f"--baseline has {len(args.baseline)} runs and --sp {len(args.sp)}: pass one of each per seed")
    if seeded and args.names:
        raise Refused("--names labels two runs; with --baseline / --sp the sides are named baseline and SP")
    if not seeded and (args.run_a is None or args.run_b is None):
        raise Refused("pass two runs (RUN_A RUN_B) or --baseline A1 A2 ... --sp B1 B2 ...")


def compare(args) -> int:
    check_options(args)
    if args.baseline is None:
        paths = [config_of(args.run_a), config_of(args.run_b)]
        configs = load_configs(paths, ("RUN_A", "RUN_B"))
    else:
        paths, configs, seeds = pair_by_seed(args.baseline, args.sp)
    try:
        check_writable_dir(args.output_dir, "--output-dir")
    except InputError as err:
        raise Refused(str(err)) from None
    if args.baseline is None:
        compare_pair(paths, configs, args.names or default_labels(*configs), args.output_dir, args, extra={"noise": ONE_PAIR_NOTE})
        print(ONE_PAIR_NOTE)
        return 0
    pairs = []
    for seed, pair_paths, pair_configs in zip(seeds, paths, configs):
        print(f"{PROG}: seed {seed}", flush=True)
        payload = compare_pair(pair_paths, pair_configs, [f"baseline (seed {seed})", f"SP (seed {seed})"],
                               args.output_dir / f"seed-{seed}", args)
        pairs.append((seed, payload))
    write_seed_report(pairs, args.output_dir)
    return 0


def load_configs(paths: Sequence[Path], flags: Sequence[str]) -> list:
    configs = [load_saved_config(p, flag) for p, flag in zip(paths, flags)]
    data = [data_of(c) for c in configs]
    if len(set(data)) > 1:
        raise Refused(f"the runs were trained on different data ({data[0]} and {next(d for d in data if d != data[0])}): "
                      "compare runs of one scene")
    return configs


def pair_by_seed(baseline: Sequence[Path], sp: Sequence[Path]):
    """``(paths, configs, seeds)``: per seed (ascending) the baseline and SP run of that seed (``--machine.seed``)."""
    paths = [config_of(p) for p in (*baseline, *sp)]
    configs = load_configs(paths, [f"--baseline {p}" for p in baseline] + [f"--sp {p}" for p in sp])
    n = len(baseline)
    sides = {}
    for side, chunk in (("baseline", range(n)), ("sp", range(n, 2 * n))):
        by_seed: Dict[int, int] = {}
        for i in chunk:
            seed = int(configs[i].machine.seed)
            if seed in by_seed:
                raise Refused(f"--{side} has two runs of seed {seed} ({paths[by_seed[seed]]} and {paths[i]}): one run per seed a side")
            by_seed[seed] = i
        sides[side] = by_seed
    if set(sides["baseline"]) != set(sides["sp"]):
        raise Refused(f"the sides were trained at different seeds (baseline {sorted(sides['baseline'])}, SP {sorted(sides['sp'])}): "
                      "pair each baseline with the SP run of its seed")
    seeds = sorted(sides["baseline"])
    pairs = [(sides["baseline"][s], sides["sp"][s]) for s in seeds]
    return [[paths[a], paths[b]] for a, b in pairs], [[configs[a], configs[b]] for a, b in pairs], seeds


def compare_pair(paths: Sequence[Path], configs: Sequence, labels: Sequence[str], out: Path, args,
                 extra: Optional[dict] = None) -> dict:
    """One pair's report in ``out`` (views, curves, meshes, table, page, JSON, ``extra`` added to the JSON); returns
    the JSON's content."""
    data = [data_of(c) for c in configs]
    runs = [Run(label, path, config) for label, path, config in zip(labels, paths, configs)]
    for run, flag in zip(runs, ("RUN_A", "RUN_B")):
        run.pipeline, run.step = setup_pipeline(run.config_path, run.config, flag, test_mode="test")
    views = [[str(Path(f).resolve()) for f in r.pipeline.datamanager.eval_dataset._dataparser_outputs.image_filenames]
             for r in runs]
    if views[0] != views[1]:
        raise Refused(f"the runs hold out different views ({len(views[0])} and {len(views[1])} images, "
                      f"first {Path(views[0][0]).name if views[0] else '-'} and {Path(views[1][0]).name if views[1] else '-'}): "
                      "compare two runs with the same dataparser settings")
    train_dataset = getattr(runs[0].pipeline.datamanager, "train_dataset", None)
    trained_on = [str(Path(f).resolve()) for f in train_dataset._dataparser_outputs.image_filenames] if train_dataset else []
    kind = scored_kind(trained_on, views[0])
    out.mkdir(parents=True, exist_ok=True)
    print(f"{PROG}: rendering {len(views[0]) if args.max_views is None else min(args.max_views, len(views[0]))} {kind} "
          "of each run", flush=True)
    images = [render_views(run, args.max_views) for run in runs]
    figures: Dict[str, Path] = {}
    views_figure(images[0], images[1], runs, out / "views.png")
    figures[f"{kind[0].upper()}{kind[1:]}: truth, both renders, both errors (one colour scale)"] = out / "views.png"
    fit_only = None if kind == HELD_OUT else (f"The scored views are {kind}: this run's dataparser does not hold them "
                                              "out, so their PSNR and SSIM measure the fit to training images, not new views.")
    notes = [fit_only] if fit_only else []
    for run in runs:
        read_curves(run)
    if curves_figure(runs, out / "curves.png"):
        figures["Training curves (SP's alpha dotted)"] = out / "curves.png"
    else:
        notes.append("No training curves: neither run logged its loss at two steps or more (train with --vis tensorboard or "
                     "viewer+tensorboard, and --logging.steps-per-log below the run's length).")
    gt = None
    gt_path = args.gt_mesh or (data[0].parent / "gt_mesh.ply" if data[0] is not None else None)
    if gt_path is not None and gt_path.is_file():
        import trimesh

        gt = trimesh.load(gt_path, force="mesh")
    elif args.gt_mesh is not None:
        raise Refused(f"--gt-mesh {args.gt_mesh}: file not found")
    for run in runs:
        mesh_of(run, args.mesh_resolution, gt)
    if runs[0].mesh and runs[1].mesh:
        from sp_plugins.geometry import save_mesh  # defers trimesh to a pair with meshes

        for run, name in zip(runs, ("a", "b")):
            save_mesh(run.mesh.pop("mesh"), out / f"mesh_{name}.ply")
        notes.append(f"Meshes at {args.mesh_resolution}^3: mesh_a.ply, mesh_b.ply"
                     + (f"; metrics against {gt_path}" if gt is not None else "; no true mesh at hand (--gt-mesh)"))
    rows = table(runs, kind)
    payload = {
        "runs": [{"label": r.label, "config": str(r.config_path), "step": r.step, "seed": int(r.config.machine.seed),
                  "sp": sp_summary(r.config), "overall": r.overall, "views": r.views,
                  "mesh": {k: v for k, v in (r.mesh or {}).items() if k != "mesh"} or None}
                 for r in runs],
        "held_out_views": [Path(v).name for v in views[0]],
        "scored_views": kind,
        "table": rows,
        **(extra or {}),
    }
    (out / "compare.json").write_text(json.dumps(payload, indent=1))
    write_html(runs, rows, figures, notes, out / "compare.html", kind)
    print_table(rows)
    if fit_only:
        print(fit_only)
    print(f"wrote {out / 'compare.html'}, {out / 'compare.json'}, " + ", ".join(str(p) for p in figures.values()))
    return payload


# -- over seeds ------------------------------------------------------------------------------------
SUMMARY_METRICS = (
    ("psnr", "PSNR (dB)", "overall", True), ("ssim", "SSIM", "overall", True), ("lpips", "LPIPS", "overall", False),
    ("chamfer", "Chamfer (of the true diagonal)", "mesh", False), ("fscore", "F-score @1%", "mesh", True),
    ("normal_consistency", "normal consistency", "mesh", True),
)
"""(key, label, where in a run's JSON, higher is better) of the metrics summarised over seeds."""


def seed_summary(pairs: Sequence[tuple]) -> List[dict]:
    """Per metric both runs of every pair have: each side's values by seed, mean and sd, and the paired
    difference SP - baseline with its interval and verdict. ``pairs``: ``(seed, payload)`` as
    :func:`compare_pair` returns them (run 0 the baseline, run 1 SP)."""
    out = []
    for key, label, where, higher in SUMMARY_METRICS:
        values = [[(run.get(where) or {}).get(key) for run in payload["runs"]] for _, payload in pairs]
        if not values or any(v is None or not math.isfinite(v) for pair in values for v in pair):
            continue
        a, b = [v[0] for v in values], [v[1] for v in values]
        (ma, sa), (mb, sb) = spread(a), spread(b)
        out.append({"metric": key, "label": label, "higher_is_better": higher, "seeds": [seed for seed, _ in pairs],
                    "baseline": a, "sp": b, "baseline_mean": ma, "baseline_sd": sa, "sp_mean": mb, "sp_sd": sb,
                    "difference": paired_difference(a, b, higher_is_better=higher).as_dict()})
    return out


def _mean_sd(mean: float, sd: Optional[float]) -> str:
    return f"{mean:.4g}" + (f" ± {sd:.2g}" if sd is not None else "")


def summary_table(summary: Sequence[dict], kind: str) -> List[List[str]]:
    """Rows of the over-seeds table: metric, baseline mean ± sd, SP mean ± sd, SP - baseline [95% interval], verdict."""
    n = len(summary[0]["seeds"]) if summary else 0
    rows = [["", f"baseline ({n} seeds)", f"SP ({n} seeds)", "SP - baseline [95% t interval]", "verdict for SP"]]
    for item in summary:
        d = item["difference"]
        label = f"{item['label']}, {kind}" if item["metric"] in ("psnr", "ssim", "lpips") else item["label"]
        interval = f"{d['mean']:+.3g}" + (f" [{d['low']:+.3g}, {d['high']:+.3g}]" if d["low"] is not None else "")
        rows.append([label, _mean_sd(item["baseline_mean"], item["baseline_sd"]), _mean_sd(item["sp_mean"], item["sp_sd"]),
                     interval, d["verdict"]])
    return rows


def per_seed_table(summary: Sequence[dict]) -> List[List[str]]:
    """One row per seed: each metric's baseline -> SP."""
    rows = [["seed"] + [item["label"] + " (baseline -> SP)" for item in summary]]
    for i, seed in enumerate(summary[0]["seeds"] if summary else []):
        rows.append([str(seed)] + [f"{item['baseline'][i]:.4g} -> {item['sp'][i]:.4g}" for item in summary])
    return rows


def seeds_figure(summary: Sequence[dict], path: Path) -> None:
    """Per metric, every seed's baseline and SP value joined by a line (the pairing), and each side's mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(summary), figsize=(2.6 * len(summary), 3.2), squeeze=False)
    for ax, item in zip(axes[0], summary):
        for seed, a, b in zip(item["seeds"], item["baseline"], item["sp"]):
            ax.plot([0, 1], [a, b], color="0.6", lw=1, marker="o", ms=4)
            ax.annotate(str(seed), (1.03, b), fontsize=7, va="center")
        ax.plot([0, 1], [item["baseline_mean"], item["sp_mean"]], color="tab:red", lw=2, marker="_", ms=16, label="mean")
        d = item["difference"]
        ax.set_title(f"{item['label']}\n{d['verdict']}", fontsize=8)
        ax.set_xticks([0, 1], ["baseline", "SP"])
        ax.set_xlim(-0.3, 1.3)
        ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_seed_report(pairs: Sequence[tuple], out: Path) -> None:
    esc = html.escape
    kinds = {payload["scored_views"] for _, payload in pairs}
    kind = kinds.pop() if len(kinds) == 1 else "views"
    summary = seed_summary(pairs)
    rows, seed_rows = summary_table(summary, kind), per_seed_table(summary)
    figure = out / "seeds.png"
    if summary:
        seeds_figure(summary, figure)
    payload = {"seeds": [seed for seed, _ in pairs], "scored_views": kind, "summary": summary, "table": rows,
               "per_seed": seed_rows, "pairs": {str(seed): f"seed-{seed}/compare.json" for seed, _ in pairs},
               "interval": "95% Student t over the seed pairs (n - 1 degrees of freedom)"}
    (out / "compare.json").write_text(json.dumps(payload, indent=1))

    def html_table(table_rows):
        head = "".join(f"<th>{esc(c)}</th>" for c in table_rows[0])
        body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in table_rows[1:])
        return f"<table><tr>{head}</tr>{body}</table>"

    links = "".join(f'<li><a href="seed-{seed}/compare.html">seed {seed}</a>: '
                    + ", ".join(f"<code>{esc(r['config'])}</code>" for r in p["runs"]) + "</li>" for seed, p in pairs)
    image = f'<h2>Every seed</h2><img alt="every seed" src="{_inline(figure)}">' if summary else ""
    text = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>sp-compare: baseline vs SP over {len(pairs)} seeds</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:.3em .6em;text-align:right}}td:first-child,th:first-child{{text-align:left}}
img{{max-width:100%}}</style></head>
<body><h1>sp-compare: baseline vs SP over {len(pairs)} seeds</h1>
<h2>Paired by seed</h2>{html_table(rows)}
<p>Differences are SP minus baseline, seed by seed; the interval is a 95% Student t interval over the seed pairs. A verdict
says better or worse only when the interval excludes 0.</p>
{image}
<h2>Per seed</h2>{html_table(seed_rows)}
<ul>{links}</ul>
</body></html>
"""
    (out / "compare.html").write_text(text)
    print()
    print_table(rows)
    print()
    print_table(seed_rows)
    print(f"wrote {out / 'compare.html'}, {out / 'compare.json'}" + (f", {figure}" if summary else ""))


def entrypoint() -> None:
    registry.install_for_process("host_warnings", command=PROG)
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
