"""Sparse views: MipNeRF vs FreeNeRF-lite vs MipNeRF + SP, paired, resumable per run.

Every run of a *group* (one scene, number of views, seed and budget) starts from the same weights
(the RNG seeded before each model is built; MipNeRF, FreeNeRF-lite and MipNeRF + SP build the same
MLP, and each result records a digest of its initial field weights to prove it) and sees the same
rays and jitter at every step (re-seeded per step, ``bench.harness.lockstep``). So a run trained
in a later process is still paired with the ones already done: each run's result is its own JSON
(``bench/out/sparse_views/<tag>/<group>/<run>.json``), finished runs are skipped, and an SP screen
adds settings to a group without training its baseline again. The runs trained in one process
alternate step by step, so their per-step times are measured under the same load.

The runs: ``mipnerf`` (``sp-mipnerf`` with SP off), ``freenerf-lite`` (FreeNeRF's frequency mask
to ``freq_reg_end`` of training and its occlusion term; ``M`` scaled from FreeNeRF's 10 of 128 to
this budget's coarse samples unless given) and one ``sp[ALPHA0@END]`` (``:grid``: a learned alpha
grid) per SP setting: alpha0 in scene units (the object's radius is 0.85, the backdrop's 8), END a
fraction of training. Scenes: the DTU-like scene (``sp-scene --dtu-like``) of any mesh (a key of
``bench.harness.radiance.SCENES`` or a mesh file), N of its 49 views, scored on its 3 held-out views:
PSNR of the whole image and inside the object mask, SSIM whole and masked (RegNeRF / FreeNeRF's
DTU protocol: the background set to white in both images), background opacity. LPIPS needs AlexNet
weights that are not downloaded here (no network): it is reported only where they are cached.
``--white`` trains on the white-background Blender-like scene of the earlier 6-view study instead
(24 views of 64x64, 8 test views, whole-image metrics).

Usage (one thread each; see docs/results/sparse-views.md)::

    # the SP screen at the cheapest size that fails (3 views, 2000 steps, lr 2e-3)
    python -m bench.sparse_views --scenes spot --views 3 --seeds 0 --tag screen \\
        --sp 0.04@0.333 0.15@0.333 0.4@0.333 1.0@0.333 0.4@0.1 0.4@0.7 0.04@0.333:grid 0.4@0.333:grid
    # the table: the best screen setting and the paper's preset, 2 meshes x 3 / 6 / 9 views x 3 seeds
    python -m bench.sparse_views --scenes spot cow --views 3 6 9 --seeds 0 1 2 --tag table --sp 0.04@0.333 BEST
    python -m bench.sparse_views --summary --tag screen          # the markdown table of what is done
    python -m bench.radiance_methods mipnerf --dtu-like --quick MESH   # one triple on any mesh, one last line
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import math
import statistics
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from bench.harness import nerfstudio as ns
from bench.harness import radiance as rd
from bench.harness.common import machine_info, safe_name, start
from bench.harness.metrics import fmt, render_grid, table
from bench.harness.scenes import object_mask_paths

BASELINE = "mipnerf"
FREENERF = "freenerf-lite"
QUICK = dict(views=3, steps=2000, lr=2e-3)
"""The cheapest size at which MipNeRF fails on the DTU-like Spot (11.4 dB inside the object
with 3 views, 24.4 dB with all 49): the size of ``--quick`` and of the screen."""
PRESET = "0.04@0.333"
"""sp-mipnerf's preset: alpha0 0.04, exponential to 0 at a third of training."""
SPARSE = "1.0@0.333"
"""The sparse-view setting this study recommends: alpha0 about the object's radius (0.85 for the
DTU-like scenes' normalised meshes, in the units of their cameras), to 0 at a third of training. On 3 views it lifts
MipNeRF's whole-image SSIM beyond the seed spread on every seed measured where the preset does
nothing (``docs/results/sparse-views.md``)."""


def out_dir() -> Path:
    return rd.OUT.parent / "sparse_views"


@dataclasses.dataclass(frozen=True)
class SPSetting:
    """One SP run: alpha0 in scene units, ``end`` a fraction of training, optionally a learned
    alpha grid (initialised to alpha0, the paper's Neuralangelo variant)."""

    alpha0: float
    end: float
    grid: bool = False

    @property
    def name(self) -> str:
        return f"sp[{self.alpha0:g}@{self.end:g}{',grid' if self.grid else ''}]"

    @staticmethod
    def parse(text: str) -> "SPSetting":
        """``ALPHA0@END[:grid]``, e.g. ``0.4@0.333`` or ``0.04@0.333:grid``."""
        head, _, tail = text.partition(":")
        try:
            alpha0, end = (float(v) for v in head.split("@"))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected ALPHA0@END[:grid], e.g. 0.4@0.333") from None
        if tail not in ("", "grid") or not (alpha0 > 0 and 0 < end <= 1):
            raise argparse.ArgumentTypeError(f"{text!r}: expected ALPHA0@END[:grid] with alpha0 > 0 and END a fraction of training in (0, 1]")
        return SPSetting(alpha0, end, tail == "grid")


@dataclasses.dataclass(frozen=True)
class FreeNeRFSetting:
    freq_reg_end: float = 0.7
    occ_reg_mult: float = 0.01
    occ_reg_range: Optional[int] = None
    """None: FreeNeRF's 10 of 128 samples scaled to the budget's coarse samples (the same stretch of each ray)."""

    def range_for(self, coarse: int) -> int:
        return self.occ_reg_range if self.occ_reg_range is not None else max(1, round(10 * coarse / 128))


@dataclasses.dataclass(frozen=True)
class RunSpec:
    name: str
    kind: str  # "mipnerf" | "freenerf" | "sp"
    sp: Optional[SPSetting] = None
    freenerf: Optional[FreeNeRFSetting] = None

    def settings(self) -> dict:
        return {"kind": self.kind, "sp": dataclasses.asdict(self.sp) if self.sp else None,
                "freenerf": dataclasses.asdict(self.freenerf) if self.freenerf else None}


def run_specs(sp: Sequence[SPSetting], freenerf: Optional[FreeNeRFSetting] = FreeNeRFSetting(), baseline: bool = True) -> List[RunSpec]:
    specs = [RunSpec(BASELINE, "mipnerf")] if baseline else []
    if freenerf is not None:
        specs.append(RunSpec(FREENERF, "freenerf", freenerf=freenerf))
    specs += [RunSpec(s.name, "sp", sp=s) for s in sp]
    return specs


def group_name(scene: str, budget: "rd.MipBudget", seed: int) -> str:
    """What every run of a group shares; the SP fields of the budget are the old study's, not ours."""
    shared = dataclasses.replace(budget, alpha0=0.0, end=0)
    return f"{Path(scene).stem}_{budget.views}v_s{seed}_{rd.budget_key(scene, shared, seed)}"


def run_config(spec: RunSpec, data: Path, budget: "rd.MipBudget", seed: int, work: Path):
    safe = safe_name(spec.name).replace("@", "at")
    if spec.kind == "freenerf":
        assert spec.freenerf is not None
        config = rd.mip_config(False, data, budget, seed, work, method="freenerf-lite", name=safe)
        m = config.pipeline.model
        m.freq_reg_end = spec.freenerf.freq_reg_end
        m.occ_reg_mult = spec.freenerf.occ_reg_mult
        m.occ_reg_range = spec.freenerf.range_for(budget.coarse)
    else:
        config = rd.mip_config(spec.kind == "sp", data, budget, seed, work, name=safe)
    sp = spec.sp or SPSetting.parse(PRESET)  # runs with SP off still validate a schedule: the preset's fits any length
    m = config.pipeline.model
    m.sp = dataclasses.replace(m.sp, alpha0=sp.alpha0, end=sp.end, alpha_grid=sp.grid)
    return config


def weights_digest(model) -> str:
    """sha1 of the field's parameters: equal across a group when the runs start from the same weights."""
    h = hashlib.sha1()
    for name, p in sorted(model.field.named_parameters()):
        h.update(name.encode())
        h.update(p.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def scene_data(scene: str, budget: "rd.MipBudget", up_axis: Optional[str]) -> Path:
    if budget.dtu_like:
        return rd.dtu_scene_dir(scene, up_axis) if up_axis else rd.dtu_scene_dir(scene)
    return rd.scene_dir(scene, 24, budget.image, budget.test_views)


def save_renders(run: "ns.Run", path: Path) -> None:
    """The run's held-out renders (and ground truth), uint8, for figures made later."""
    import numpy as np

    arrays = {}
    for i, (gt, rgb, _) in enumerate(run.renders):
        arrays[f"gt{i}"] = (gt.numpy() * 255).round().astype(np.uint8)
        arrays[f"rgb{i}"] = (rgb.numpy() * 255).round().astype(np.uint8)
    np.savez_compressed(path, **arrays)


def group_figure(folder: Path, names: Sequence[str]) -> Optional[Path]:
    """Rows: held-out views; columns: ground truth, then each run (baseline | FreeNeRF-lite | SP ...)."""
    import numpy as np

    have = [n for n in names if (folder / f"{n}.npz").is_file()]
    if not have:
        return None
    renders = {n: np.load(folder / f"{n}.npz") for n in have}
    views = len([k for k in renders[have[0]].files if k.startswith("rgb")])
    columns = {n: [(renders[n][f"rgb{v}"], None) for v in range(views)] for n in have}
    return render_grid(columns, [renders[have[0]][f"gt{v}"] for v in range(views)], folder / "renders.png")


def study(scene: str, budget: "rd.MipBudget", seed: int, specs: Sequence[RunSpec], tag: str, overwrite: bool = False,
          up_axis: Optional[str] = None) -> Dict[str, dict]:
    """Train the runs of ``specs`` not done yet in this group (together, alternating), write one JSON
    each; returns every requested run's result. Refuses a group whose runs did not start alike."""
    folder = out_dir() / tag / group_name(scene, budget, seed)
    paths = {s.name: folder / f"{s.name}.json" for s in specs}
    todo = [s for s in specs if overwrite or not paths[s.name].is_file()]
    if todo:
        data = scene_data(scene, budget, up_axis)
        work = rd.OUT / "runs" / f"sparse-{folder.name}"
        runs = {s.name: ns.Run(s.name, run_config(s, data, budget, seed, work), seed) for s in todo}
        digests = {name: weights_digest(run.model) for name, run in runs.items()}
        wall = ns.train_together(runs, budget.steps, seed, f"sparse/{folder.name}", log_every=max(100, budget.steps // 10))
        masks = None
        folder.mkdir(parents=True, exist_ok=True)
        for spec in todo:
            run = runs[spec.name]
            if budget.dtu_like:
                masks = object_mask_paths(data, run.trainer.pipeline.datamanager.eval_dataset.image_filenames)
            t0 = time.perf_counter()
            metrics = run.evaluate("rgb_fine", "accumulation_fine", masks)
            result = {
                "study": "sparse_views", "tag": tag, "scene": scene, "seed": seed, "run": spec.name, **spec.settings(),
                "budget": dataclasses.asdict(budget), "group": folder.name, "init_weights": digests[spec.name],
                "trained_with": list(runs), "train_wall_s": wall, "eval_s": time.perf_counter() - t0,
                **ns.run_summary(run, metrics), "machine": machine_info(),
            }
            if spec.kind == "freenerf":
                result["freenerf"]["occ_reg_range_used"] = run.model.config.occ_reg_range
            paths[spec.name].write_text(json.dumps(result, indent=1))
            save_renders(run, folder / f"{spec.name}.npz")
            logging.info("%s %s: PSNR %.2f (object %s), SSIM %.3f", folder.name, spec.name, result["psnr"],
                         fmt(result.get("psnr_object")), result["ssim"])
        group_figure(folder, [s.name for s in specs])
    results = {s.name: json.loads(paths[s.name].read_text()) for s in specs}
    starts = {r["init_weights"] for r in results.values()}
    if len(starts) > 1:
        raise RuntimeError(f"{folder}: its runs started from different weights ({sorted(starts)}): they are not paired; "
                           "rerun the group with --overwrite")
    return results


# -- summaries ----------------------------------------------------------------------------------


def collect(tag: str) -> List[dict]:
    return [json.loads(p.read_text()) for p in sorted((out_dir() / tag).glob("*/*.json"))]


def _mean_spread(values: Sequence[float]) -> str:
    values = [v for v in values if v is not None and not math.isnan(v)]
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.2f}"
    return f"{statistics.mean(values):.2f} ± {statistics.stdev(values):.2f}"


def summary(results: Sequence[dict]) -> str:
    """Per (scene, views, run): mean ± standard deviation over seeds, and the paired difference to
    the baseline of the same seed (how many seeds are ahead by more than the baseline's seed spread,
    in object PSNR and in whole-image SSIM, the paper's table metric)."""
    groups: Dict[Tuple[str, int, str], List[dict]] = {}
    base: Dict[Tuple[str, int, int], dict] = {}
    for r in results:
        key = (Path(r["scene"]).stem, r["budget"]["views"], r["run"])
        groups.setdefault(key, []).append(r)
        if r["run"] == BASELINE:
            base[(key[0], key[1], r["seed"])] = r
    rows = []
    for (scene, views, run), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2] != BASELINE, kv[0][2])):
        obj = [r.get("psnr_object") for r in rs]
        paired = [(r.get("psnr_object") or r["psnr"]) - (b.get("psnr_object") or b["psnr"])
                  for r in rs for b in [base.get((scene, views, r["seed"]))] if b is not None]
        spread = [b.get("psnr_object") or b["psnr"] for (s, v, _), b in base.items() if (s, v) == (scene, views)]
        margin = statistics.stdev(spread) if len(spread) > 1 else 0.0
        ahead = "" if run == BASELINE else f"{sum(d > margin for d in paired)} / {len(paired)}"
        paired_ssim = [r["ssim"] - b["ssim"] for r in rs for b in [base.get((scene, views, r["seed"]))] if b is not None]
        spread_ssim = [b["ssim"] for (s, v, _), b in base.items() if (s, v) == (scene, views)]
        margin_ssim = statistics.stdev(spread_ssim) if len(spread_ssim) > 1 else 0.0
        ahead_ssim = "" if run == BASELINE else f"{sum(d > margin_ssim for d in paired_ssim)} / {len(paired_ssim)}"
        diff = "" if run == BASELINE or not paired else _interval(paired, 2)
        diff_ssim = "" if run == BASELINE or not paired_ssim else _interval(paired_ssim, 2)
        rows.append((scene, views, run, len(rs), _mean_spread([r["psnr"] for r in rs]), _mean_spread(obj), diff, ahead,
                     _mean_spread([r["ssim"] for r in rs]), diff_ssim, ahead_ssim, _mean_spread([r.get("ssim_object") for r in rs]),
                     f"{statistics.mean(r['median_step_s'] for r in rs):.3f}"))
    return table(["scene", "views", "run", "seeds", "PSNR", "PSNR object", "vs baseline (object) [95% t]", "ahead / seeds",
                  "SSIM", "SSIM vs baseline [95% t]", "SSIM ahead / seeds", "SSIM object", "s/step"], rows)


def _interval(differences: Sequence[float], digits: int) -> str:
    """A paired difference over seeds with its 95% Student-t interval (``sp_plugins.stats``, as ``sp-compare``)."""
    from sp_plugins.stats import paired_difference

    return paired_difference([0.0] * len(differences), list(differences)).text(digits)  # b - 0: the differences


def quick_line(results: Dict[str, dict], sp_name: str) -> str:
    """``baseline PSNR X, SP PSNR Y, FreeNeRF PSNR Z (object)``: inside the object mask on the
    DTU-like scene, the whole image otherwise."""
    key = "psnr_object" if "psnr_object" in results[BASELINE] else "psnr"
    where = "object" if key == "psnr_object" else "whole image"
    return (f"baseline PSNR {results[BASELINE][key]:.2f}, SP PSNR {results[sp_name][key]:.2f}, "
            f"FreeNeRF PSNR {results[FREENERF][key]:.2f} ({where})")


def quick(mesh: str, budget: "rd.MipBudget", seed: int = 0, tag: str = "quick", sp: Optional[SPSetting] = None,
          up_axis: Optional[str] = None, overwrite: bool = False) -> str:
    """One triple (baseline, SP, FreeNeRF-lite) on ``mesh``; returns :func:`quick_line`."""
    sp = sp or SPSetting.parse(SPARSE)
    results = study(mesh, budget, seed, run_specs([sp]), tag, overwrite, up_axis)
    return quick_line(results, sp.name)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["spot"], help="keys of bench.harness.radiance.SCENES or mesh files")
    parser.add_argument("--up-axis", choices=["x", "y", "z"], help="of a mesh file (known meshes: their own)")
    parser.add_argument("--views", nargs="+", type=int, default=[QUICK["views"]])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--sp", nargs="*", type=SPSetting.parse, default=[SPSetting.parse(PRESET), SPSetting.parse(SPARSE)],
                        help=f"ALPHA0@END[:grid] ... (default: the preset {PRESET} and the sparse-view setting {SPARSE})")
    parser.add_argument("--no-freenerf", action="store_true", help="skip the FreeNeRF-lite run")
    parser.add_argument("--freq-reg-end", type=float, default=FreeNeRFSetting.freq_reg_end)
    parser.add_argument("--occ-reg-mult", type=float, default=FreeNeRFSetting.occ_reg_mult)
    parser.add_argument("--occ-reg-range", type=int, default=None, help="samples (default: 10 x coarse / 128)")
    parser.add_argument("--white", action="store_true", help="the white-background Blender-like scene (not DTU-like)")
    parser.add_argument("--steps", type=int, default=QUICK["steps"])
    parser.add_argument("--lr", type=float, default=QUICK["lr"])
    for name in ("rays", "coarse", "fine", "mlp_num_layers", "mlp_layer_width", "head_width"):
        parser.add_argument("--" + name.replace("_", "-"), type=int, default=getattr(rd.MipBudget, name))
    parser.add_argument("--tag", default="screen")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--summary", action="store_true", help="only print the table of --tag")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    start(args.threads, quiet=("nerfstudio", "PIL", "sp_plugins"))
    t0 = time.time()
    if not args.summary:
        freenerf = None if args.no_freenerf else FreeNeRFSetting(args.freq_reg_end, args.occ_reg_mult, args.occ_reg_range)
        for scene in args.scenes:
            for views in args.views:
                budget = rd.MipBudget(steps=args.steps, lr=args.lr, views=views, dtu_like=not args.white, rays=args.rays,
                                      coarse=args.coarse, fine=args.fine, mlp_num_layers=args.mlp_num_layers,
                                      mlp_layer_width=args.mlp_layer_width, head_width=args.head_width)
                for seed in args.seeds:
                    study(scene, budget, seed, run_specs(args.sp, freenerf), args.tag, args.overwrite, args.up_axis)
    table = summary(collect(args.tag))
    path = out_dir() / f"{args.tag}.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(table + "\n")
    print(table)
    print(f"\nwall time {time.time() - t0:.0f} s; machine: {machine_info()}")


if __name__ == "__main__":
    main()
