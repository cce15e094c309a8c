"""``sp-compare``: two nerfstudio runs side by side, e.g. a method and its SP version on the same data and seed.

    sp-compare outputs/baseline/nerfacto/RUN outputs/sp/nerfacto/RUN --output-dir compare

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

from sp_plugins.cli.run_folder import Refused, answer, model_sdf

PROG = "sp-compare"
CURVES = {"loss": "Train Loss", "psnr": "Train Metrics Dict/psnr", "alpha": "Train Metrics Dict/sp_alpha"}
"""Event-file tags nerfstudio's writer gives the training loss, the training PSNR and our models' ``sp_alpha``."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0].split(": ", 1)[1])
    parser.add_argument("run_a", type=Path, help="a run folder ns-train wrote (holding config.yml), or its config.yml")
    parser.add_argument("run_b", type=Path, help="the other run, on the same data")
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
    from sp_plugins.geometry import mesh_metrics, sparse_extract_mesh

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


def compare(args) -> int:
    from sp_plugins.cli.run_folder import load_saved_config, setup_pipeline

    if args.max_views is not None and args.max_views < 1:
        raise Refused(f"--max-views {args.max_views}: must be at least 1")
    if args.mesh_resolution < 16:
        raise Refused(f"--mesh-resolution {args.mesh_resolution}: need at least 16 cells (128 and up for a useful mesh)")
    paths = [config_of(args.run_a), config_of(args.run_b)]
    configs = [load_saved_config(p, flag) for p, flag in zip(paths, ("RUN_A", "RUN_B"))]
    data = [data_of(c) for c in configs]
    if data[0] != data[1]:
        raise Refused(f"the runs were trained on different data ({data[0]} and {data[1]}): compare two runs of one scene")
    from sp_plugins.adapter.checks import check_writable_dir
    from sp_plugins.adapter.errors import InputError

    try:
        check_writable_dir(args.output_dir, "--output-dir")
    except InputError as err:
        raise Refused(str(err)) from None
    labels = args.names or default_labels(*configs)
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
    out = args.output_dir
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
        from sp_plugins.geometry import save_mesh

        for run, name in zip(runs, ("a", "b")):
            save_mesh(run.mesh.pop("mesh"), out / f"mesh_{name}.ply")
        notes.append(f"Meshes at {args.mesh_resolution}^3: mesh_a.ply, mesh_b.ply"
                     + (f"; metrics against {gt_path}" if gt is not None else "; no true mesh at hand (--gt-mesh)"))
    rows = table(runs, kind)
    payload = {
        "runs": [{"label": r.label, "config": str(r.config_path), "step": r.step, "sp": sp_summary(r.config),
                  "overall": r.overall, "views": r.views, "mesh": {k: v for k, v in (r.mesh or {}).items() if k != "mesh"} or None}
                 for r in runs],
        "held_out_views": [Path(v).name for v in views[0]],
        "scored_views": kind,
        "table": rows,
    }
    (out / "compare.json").write_text(json.dumps(payload, indent=1))
    write_html(runs, rows, figures, notes, out / "compare.html", kind)
    print_table(rows)
    if fit_only:
        print(fit_only)
    print(f"wrote {out / 'compare.html'}, {out / 'compare.json'}, " + ", ".join(str(p) for p in figures.values()))
    return 0


def entrypoint() -> None:
    from sp_plugins.patches import registry

    registry.install_for_process("host_warnings", command=PROG)
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
