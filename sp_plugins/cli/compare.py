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
weights-only checkpoint); nothing here changes a run folder. This module opens, pairs, renders and scores the runs;
the report (figures, tables, pages, the summary over seeds) is :mod:`sp_plugins.cli.compare_report`'s.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from sp_plugins.adapter.checks import check_writable_dir
from sp_plugins.adapter.errors import InputError
from sp_plugins.cli.run_folder import Refused, answer, load_saved_config, model_sdf, setup_pipeline
from sp_plugins.patches import registry
from sp_plugins.cli.compare_report import (
    HELD_OUT,
    Run,
    curves_figure,
    print_table,
    sp_summary,
    table,
    views_figure,
    write_html,
    write_seed_report,
)

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




def entrypoint() -> None:
    registry.install_for_process("host_warnings", command=PROG)
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
