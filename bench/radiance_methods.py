"""Radiance methods in nerfstudio: ReLU fields (hierarchy / flat / flat + SP) and sparse-view MipNeRF.

Three studies, each trained through nerfstudio's own trainers, driven step by step in ONE process
with the runs alternating (A B C, C B A, ...) and the RNG re-seeded per step, so every run sees the
same rays and jitter and the per-step times are measured under the same machine load:

- ``relu``: ``relu-field`` (4-stage coarse-to-fine), ``relu-field-flat`` and one or more
  ``sp-relu-field`` variants (alpha0 in *voxels* of the full grid, end as a fraction of training),
  at equal steps on synthetic scenes (24 views of 64x64, Blender layout scaled by 1.5 so the
  object fills the [-1.5, 1.5]^3 box like a [-1, 1]^3 box with the usual 0.85 radius).
  ``--paper-regime`` sets thr3ed_atom's ratios at CPU size (:data:`PAPER_REGIME`: about one voxel
  per pixel, samples and pixels under a voxel, thousands of samples per voxel; cell grid,
  world-unit density, L1, lr restarted per stage); ``--methods`` also takes ``relu-field-flat-sp-lr``,
  flat training with the SP runs' later lr decay, so SP's effect is not confused with its schedule's. Every run
  reports train-view PSNR next to test PSNR.
- ``mipnerf``: ``sp-mipnerf`` with SP off (plain MipNeRF) and on, trained on 6 of the 24 views,
  a CPU-sized MipNeRF (narrower MLP, fewer rays and samples: stated in the results); with
  ``--dtu-like`` on 3 / 6 / 9 of the 49 views of the DTU-like scene, scored inside the object mask too.
- ``cost``: the SP per-step cost of the ReLU field split into SP's own arithmetic (noise,
  reflection) and the slower grid lookups at perturbed positions, plus the average over a schedule.

Metrics per run, on the held-out test views: PSNR, SSIM, and *background opacity*: the mean
rendered opacity over pixels whose true alpha is 0 (floaters and fog that should not be there).
LPIPS needs AlexNet weights that are not downloaded here: it is reported only when cached.

Usage::

    python -m bench.radiance_methods relu                  # the final ReLU table (resumable)
    python -m bench.radiance_methods relu --scenes spot --steps 300 --tag probe   # a quick probe
    python -m bench.radiance_methods relu --paper-regime --scenes spot --tag paper16 \
        --methods relu-field relu-field-flat relu-field-flat-sp-lr --sp 0.25@0.2857   # thr3ed_atom's ratios
    python -m bench.radiance_methods mipnerf
    python -m bench.radiance_methods mipnerf --dtu-like --views 3 --steps 2000 --end 667 --tag dtu --scenes spot   # DTU-like, object-masked PSNR
    python -m bench.radiance_methods mipnerf --dtu-like --quick MESH   # mipnerf / sp-mipnerf / freenerf-lite (bench.sparse_views)
    python -m bench.radiance_methods cost

Finished runs (one JSON per study / scene / setting) are skipped; ``--overwrite`` recomputes.
Outputs go to ``bench/out/radiance_methods/``: JSON per run, ``<study>.md`` summary, PNGs of
loss curves and test renders.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import torch

from bench.harness import nerfstudio as ns
from bench.harness import radiance as rd
from bench.harness.common import done_or_run, machine_info, paired_timing, ratio_summary, safe_name, start
from bench.harness.metrics import fmt, loss_figure, ratio_cell, table
from bench.harness.radiance import BOX, SCALE, SCENES, MipBudget, budget_key
from bench.harness.scenes import object_mask_paths
from sp_plugins.nerfstudio.components.views import VIEW_SELECTIONS
from sp_plugins.nerfstudio.relu_field.model import voxel_size


# -- settings -----------------------------------------------------------------------------------


@dataclasses.dataclass
class ReLUBudget:
    """The CPU-sized ReLU-field setting shared by every run of a table."""

    steps: int = 1200
    """training steps of every run"""
    rays: int = 1024
    """rays per training batch"""
    num_samples: int = 96
    """samples per ray inside the grid's box"""
    resolution: int = 129
    """grid points per axis (cells per axis with ``align_corners`` False)"""
    color_mode: str = "rgb"
    """what a grid point stores besides density: rgb, or sh (spherical harmonics of ``sh_degree``)"""
    sh_degree: int = 1
    """degree of the spherical harmonics (``color_mode`` sh only)"""
    lr: float = 0.03
    """Adam learning rate of the grid at the start"""
    lr_final: float = 0.003
    """the learning rate at the last step (``lr_schedule`` exponential)"""
    density_init: Tuple[float, float] = (-1.0, 1.0)
    """the grid's raw densities start uniform in this range"""
    density_scale: float = 1.0
    """factor on the raw density before the ReLU"""
    views: int = 24
    """training views of the white-background scene"""
    test_views: int = 8
    """held-out views scored"""
    image: int = 64
    """side in pixels of the renders"""
    background: str = "white"
    """Training background: white (the data's), or random (a random colour per ray; floaters
    cannot hide in front of it). Test renders are always composited on white."""
    align_corners: bool = True
    """False: thr3ed_atom's cell grid (resolution counts cells)."""
    density_units: str = "voxel"
    """unit of ``density_scale``: per voxel of the full grid, or per world unit (thr3ed_atom's)"""
    loss: str = "mse"
    """colour loss: mse, or l1 (thr3ed_atom's)"""
    diffuse_loss_weight: float = 0.0
    """weight of thr3ed_atom's extra loss on the diffuse (SH degree-0) render; needs ``color_mode`` sh"""
    lr_schedule: str = "exponential"
    """exponential (lr -> lr_final over the run) or staged (thr3ed_atom: restart per stage, x0.1
    every decay_every of training; SP runs and relu-field-flat-sp-lr first decay at sp_first_decay)."""
    decay_every: float = 3 / 28
    """staged: fraction of training between two x0.1 decays inside a stage"""
    stage_gamma: float = 1.0
    """staged: the learning rate restarts at lr * stage_gamma^k at stage k"""
    sp_first_decay: float = 12 / 28
    """staged: the SP runs' (one stage) first decay, as a fraction of training (the paper: step 12000 of 28000)"""


PAPER_REGIME = dict(
    resolution=64, align_corners=False, image=112, views=24, rays=1024, num_samples=128, steps=6000,
    color_mode="rgb", density_units="world", density_scale=100 / 3, loss="l1", lr_schedule="staged",
    stage_gamma=0.9,
)
"""``relu --paper-regime``: thr3ed_atom's ratios at CPU size (docs/results/radiance-methods.md).
64^3 cells over [-1.5, 1.5]^3 (voxel 3/64), 24 views of 112^2 (0.87 voxels per pixel, a pixel 0.57
voxel wide at the centre), 128 samples in the box (at most 0.87 voxel apart), 1024 rays x 6000 steps
(about 3000 samples per voxel), 4 stages of 8 -> 64 cells."""


@dataclasses.dataclass(frozen=True)
class SPVariant:
    """An sp-relu-field setting: alpha0 in voxels of the full grid, ``end`` a fraction of training."""

    voxels: float
    end: float
    schedule: str = "exponential"
    final_ratio: float = 1e-3

    @property
    def name(self) -> str:
        tail = "" if self.schedule == "exponential" and self.final_ratio == 1e-3 else f"-{self.schedule}{self.final_ratio:g}"
        return f"sp-relu-field[{self.voxels:g}vox,end{self.end:g}{tail}]"

    @staticmethod
    def parse(text: str) -> "SPVariant":
        """``VOXELS@END[:SCHEDULE[:FINAL_RATIO]]``, e.g. ``8@0.3`` or ``16@0.6:exponential:0.05``."""
        try:
            head, *rest = text.split(":")
            voxels, end = head.split("@")
            return SPVariant(float(voxels), float(end), *(rest[:1] or ["exponential"]), *(float(r) for r in rest[1:2]))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected VOXELS@END[:SCHEDULE[:FINAL_RATIO]], e.g. 8@0.3") from None


# -- ReLU fields ----------------------------------------------------------------------------------


SP_LR_FLAT = "relu-field-flat-sp-lr"
"""relu-field-flat with the SP runs' learning-rate schedule (first decay at sp_first_decay): the
control that separates SP's effect from its later lr decay."""


def relu_config(name: str, data: Path, budget: ReLUBudget, variant: Optional[SPVariant], seed: int, out: Path,
                label: Optional[str] = None):
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    from sp_plugins.nerfstudio.relu_field.lr import StagedStepDecaySchedulerConfig
    from sp_plugins.adapter.shrink import shrink
    from sp_plugins.nerfstudio.runs import configure_run, method_config

    late_lr = variant is not None or name == SP_LR_FLAT
    config = method_config("relu-field-flat" if name == SP_LR_FLAT else name)
    m = config.pipeline.model
    sp = m.sp
    if variant is not None:
        voxel = voxel_size(BOX, budget.resolution, budget.align_corners)
        sp = dataclasses.replace(m.sp, enabled=True, alpha0=variant.voxels * voxel, end=variant.end,
                                 schedule=variant.schedule, final_ratio=variant.final_ratio, seed=seed)
    shrink(config, resolution=budget.resolution, num_samples=budget.num_samples, color_mode=budget.color_mode,
           sh_degree=budget.sh_degree, density_init=tuple(budget.density_init), density_scale=budget.density_scale,
           eval_num_rays_per_chunk=4096, background_color=budget.background, align_corners=budget.align_corners,
           density_units=budget.density_units, loss=budget.loss, diffuse_loss_weight=budget.diffuse_loss_weight, sp=sp,
           lr={"fields": budget.lr})
    opt = config.optimizers["fields"]
    if budget.lr_schedule == "staged":
        opt["scheduler"] = StagedStepDecaySchedulerConfig(
            max_steps=budget.steps, stages=m.hierarchy_stages, decay_every=budget.decay_every,
            first_decay=budget.sp_first_decay if late_lr else None, stage_gamma=budget.stage_gamma)
    elif budget.lr_final != budget.lr:
        opt["scheduler"] = ExponentialDecaySchedulerConfig(lr_final=budget.lr_final, max_steps=budget.steps)
    configure_run(config, data, steps=budget.steps, output_dir=out, layout="blender", rays_per_batch=budget.rays,
                  experiment_name=safe_name(label or name))
    config.pipeline.datamanager.dataparser.scale_factor = SCALE
    if budget.background == "random":  # keep the alpha channel so the loss can composite
        config.pipeline.datamanager.dataparser.alpha_color = None
    config.pipeline.datamanager.eval_num_rays_per_batch = 4096
    return config


def grid_path(result_path: Path, run_name: str) -> Path:
    return result_path.with_name(f"{result_path.stem}.{safe_name(run_name)}.grid.pt")


def relu_study(scene: str, budget: ReLUBudget, variants: Sequence[SPVariant], methods: Sequence[str], seed: int,
               tag: str, overwrite: bool, save_grids: bool = False) -> dict:
    key = budget_key(scene, budget, list(variants), list(methods), seed)
    path = rd.OUT / "relu" / f"{tag}_{scene}_{key}.json"
    return done_or_run(path, overwrite, lambda: train_relu(scene, budget, variants, methods, seed, tag, key, path, save_grids))[0]


def train_relu(scene: str, budget: ReLUBudget, variants: Sequence[SPVariant], methods: Sequence[str], seed: int, tag: str,
               key: str, path: Path, save_grids: bool) -> dict:
    data = rd.scene_dir(scene, budget.views, budget.image, budget.test_views)
    work = rd.OUT / "runs" / f"relu-{scene}-{key}"
    runs: Dict[str, ns.Run] = {}
    for name in methods:
        runs[name] = ns.Run(name, relu_config(name, data, budget, None, seed, work), seed)
    for variant in variants:
        runs[variant.name] = ns.Run(variant.name, relu_config("sp-relu-field", data, budget, variant, seed, work, variant.name), seed)
    wall = ns.train_together(runs, budget.steps, seed, f"relu/{scene}", log_every=max(100, budget.steps // 30))
    result = {"study": "relu", "tag": tag, "scene": scene, "seed": seed, "budget": dataclasses.asdict(budget),
              "variants": [dataclasses.asdict(v) for v in variants], "train_wall_s": wall, "runs": list(runs)}
    for name, run in runs.items():
        result[name] = ns.run_summary(run, {**run.evaluate(), "train_psnr": run.train_psnr()})
        logging.info("%s %s: PSNR %.2f, background opacity %.4f", scene, name, result[name]["psnr"],
                     result[name]["background_opacity"])
        if save_grids:
            path.parent.mkdir(parents=True, exist_ok=True)
            field = run.model.field
            torch.save({"grid": field.grid.detach().cpu(), "aabb": field.aabb.cpu(), "density_scale": field.density_scale},
                       grid_path(path, name))
    if "relu-field-flat" in runs:
        for variant in variants:
            result[variant.name].update(ns.active_time_ratios(runs[variant.name], runs["relu-field-flat"]))
    result["machine"] = machine_info()
    figures(runs, result, path)
    return result


def figures(runs: Dict[str, ns.Run], result: dict, path: Path) -> None:
    """Test renders and loss curves next to the result."""
    path.parent.mkdir(parents=True, exist_ok=True)
    ns.save_renders(runs, path.with_suffix(".png"))
    loss_figure([("", {name: result[name]["losses"] for name in runs})], path.with_name(path.stem + "_loss.png"))


# -- MipNeRF -----------------------------------------------------------------------------------


def mip_study(scene: str, budget: MipBudget, seed: int, tag: str, overwrite: bool) -> dict:
    key = budget_key(scene, budget, seed)
    path = rd.OUT / "mipnerf" / f"{tag}_{scene}_{key}.json"
    return done_or_run(path, overwrite, lambda: train_mip(scene, budget, seed, tag, key, path))[0]


def train_mip(scene: str, budget: MipBudget, seed: int, tag: str, key: str, path: Path) -> dict:
    data = rd.dtu_scene_dir(scene) if budget.dtu_like else rd.scene_dir(scene, 24, budget.image, budget.test_views)
    work = rd.OUT / "runs" / f"mip-{scene}-{key}"
    runs = {"mipnerf": ns.Run("mipnerf", rd.mip_config(False, data, budget, seed, work), seed),
            "sp-mipnerf": ns.Run("sp-mipnerf", rd.mip_config(True, data, budget, seed, work), seed)}
    wall = ns.train_together(runs, budget.steps, seed, f"mipnerf/{scene}")
    result = {"study": "mipnerf", "tag": tag, "scene": scene, "seed": seed, "budget": dataclasses.asdict(budget),
              "train_wall_s": wall, "runs": list(runs)}
    for name, run in runs.items():
        masks = object_mask_paths(data, run.trainer.pipeline.datamanager.eval_dataset.image_filenames) if budget.dtu_like else None
        result[name] = ns.run_summary(run, run.evaluate("rgb_fine", "accumulation_fine", masks))
        logging.info("%s %s: PSNR %.2f (object %s), background opacity %.4f", scene, name, result[name]["psnr"],
                     fmt(result[name].get("psnr_object")), result[name]["background_opacity"])
    result["sp-mipnerf"].update(ns.active_time_ratios(runs["sp-mipnerf"], runs["mipnerf"]))
    result["machine"] = machine_info()
    figures(runs, result, path)
    return result


# -- SP cost on the ReLU field -----------------------------------------------------------------


def cost_study(resolution: int, rays: int, samples: int, color_mode: str, repeats: int, voxels: float, end: float) -> dict:
    """Per-step time of a flat ReLU-field training step, alternating four variants in one process:

    - ``plain``: no SP;
    - ``sp_arithmetic``: SP's noise and reflection are computed, but the grid is read at the
      *unperturbed* positions (what SP would cost if the lookups did not slow down);
    - ``sp``: SP as trained (lookups at the perturbed positions);
    - ``sp_inactive``: SP configured but alpha = 0 (after the schedule's end): it must cost nothing.
    """
    from nerfstudio.cameras.rays import RayBundle
    from nerfstudio.data.scene_box import SceneBox

    from sp_plugins.core import SPConfig
    from sp_plugins.nerfstudio.relu_field.model import ReLUFieldModelConfig

    box = SceneBox(aabb=BOX)
    voxel = voxel_size(BOX, resolution)

    def make(sp_on: bool):
        cfg = ReLUFieldModelConfig(resolution=resolution, num_samples=samples, color_mode=color_mode,  # type: ignore[arg-type]
                                   sp=SPConfig(enabled=sp_on, alpha0=voxels * voxel, end=end, boundary="reflect"))
        torch.manual_seed(0)
        model = cfg.setup(scene_box=box, num_train_data=24)
        model.sp.set_step(0, 1000)
        model.train()
        return model, torch.optim.Adam([model.field.grid], lr=0.03, fused=True)

    g = torch.Generator().manual_seed(0)
    origins = 4.0 * torch.nn.functional.normalize(torch.randn(rays, 3, generator=g), dim=-1)
    targets = 0.6 * torch.randn(rays, 3, generator=g)
    bundle = RayBundle(origins=origins, directions=torch.nn.functional.normalize(targets - origins, dim=-1),
                       pixel_area=torch.full((rays, 1), 1e-4), camera_indices=torch.zeros(rays, 1, dtype=torch.long))
    gt = torch.rand(rays, 3, generator=g)
    models = {"plain": make(False), "sp_arithmetic": make(True), "sp": make(True), "sp_inactive": make(True)}
    models["sp_inactive"][0].sp.set_step(999, 1000)
    assert models["sp_inactive"][0].sp.alpha == 0.0
    arithmetic_field = models["sp_arithmetic"][0].field
    arithmetic_sp = models["sp_arithmetic"][0].sp
    arithmetic_field.use_preconditioner(None)
    plain_lookup = arithmetic_field.lookup

    def lookup_with_discarded_sp(x):
        arithmetic_sp(x)  # pay for the noise and the reflection, then read the grid where SP would not
        return plain_lookup(x)

    arithmetic_field.lookup = lookup_with_discarded_sp  # type: ignore[method-assign]

    def step_fn(model, opt):
        def run():
            out = model(bundle)
            loss = ((out["rgb"] - gt) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        return run

    times = paired_timing({k: step_fn(*v) for k, v in models.items()}, repeats=repeats)
    summary = ratio_summary(times, "plain")
    active = summary["sp"]["ratio_vs_plain"]
    return {
        "study": "cost",
        "resolution": resolution, "rays": rays, "samples": samples, "color_mode": color_mode,
        "alpha_voxels": voxels, "end": end, "repeats": repeats,
        "summary": summary,
        "sp_total_ratio": active,
        "sp_arithmetic_share": summary["sp_arithmetic"]["ratio_vs_plain"] - 1.0,
        "lookup_slowdown_share": active - summary["sp_arithmetic"]["ratio_vs_plain"],
        "schedule_average_ratio": end * active + (1.0 - end) * summary["sp_inactive"]["ratio_vs_plain"],
        "machine": machine_info(),
    }


# -- summaries ------------------------------------------------------------------------------


def relu_table(results: List[dict]) -> str:
    return table(["tag", "scene", "grid", "steps", "run", "train PSNR", "test PSNR", "SSIM", "bg opacity", "fg opacity",
                  "final train loss", "s/step", "SP time ratio (active / whole run)"],
                 [(r["tag"], r["scene"], f"{b['resolution']}^3 {b['color_mode']}", b["steps"], name, fmt(m.get("train_psnr")),
                   f"{m['psnr']:.2f}", f"{m['ssim']:.3f}", f"{m['background_opacity']:.4f}", f"{m['foreground_opacity']:.3f}",
                   f"{m['final_loss']:.5f}", f"{m['median_step_s']:.3f}", ratio_cell(m))
                  for r in results for b in [r["budget"]] for name in r["runs"] for m in [r[name]]])


def mip_table(results: List[dict]) -> str:
    return table(["tag", "scene", "seed", "views", "steps", "run", "test PSNR", "PSNR in object mask", "SSIM", "bg opacity",
                  "s/step", "SP time ratio (active / whole run)"],
                 [(r["tag"], f"{r['scene']} (DTU-like)" if b.get("dtu_like") else r["scene"], r["seed"], b["views"], b["steps"],
                   name, f"{m['psnr']:.2f}", fmt(m.get("psnr_object")), f"{m['ssim']:.3f}", f"{m['background_opacity']:.4f}",
                   f"{m['median_step_s']:.3f}", ratio_cell(m))
                  for r in results for b in [r["budget"]] for name in r["runs"] for m in [r[name]]])


def collect(study: str, tag: Optional[str]) -> List[dict]:
    results = []
    for path in sorted((rd.OUT / study).glob("*.json")):
        r = json.loads(path.read_text())
        if tag is None or r.get("tag") == tag:
            results.append(r)
    return results


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="study", required=True)
    relu = sub.add_parser("relu", help="relu-field vs relu-field-flat vs sp-relu-field")
    relu.add_argument("--scenes", nargs="+", default=["spot", "cow"], choices=sorted(SCENES))
    relu.add_argument("--methods", nargs="*", default=["relu-field", "relu-field-flat"],
                      choices=["relu-field", "relu-field-flat", SP_LR_FLAT])
    relu.add_argument("--paper-regime", action="store_true",
                      help="defaults of the CPU-sized thr3ed_atom regime (PAPER_REGIME); explicit flags still win")
    relu.add_argument("--sp", nargs="*", type=SPVariant.parse, default=[SPVariant(8.0, 0.3)],
                      help="sp-relu-field variants VOXELS@END[:SCHEDULE[:FINAL_RATIO]]")
    for f in dataclasses.fields(ReLUBudget):
        kind = type(f.default)
        if kind is tuple:
            relu.add_argument("--" + f.name.replace("_", "-"), nargs=2, type=float, default=f.default)
        elif kind is bool:
            relu.add_argument("--" + f.name.replace("_", "-"), type=lambda v: {"true": True, "false": False}[v.lower()],
                              default=f.default, metavar="{true,false}")
        else:
            relu.add_argument("--" + f.name.replace("_", "-"), type=kind, default=f.default)
    relu.add_argument("--save-grids", action="store_true", help="keep each run's final grid (<result>.<run>.grid.pt)")
    mip = sub.add_parser("mipnerf", help="mipnerf vs sp-mipnerf on few views")
    mip.add_argument("--scenes", nargs="+", default=["spot", "cow"], choices=sorted(SCENES))
    mip.add_argument("--quick", metavar="MESH",
                     help="one paired triple (mipnerf, sp-mipnerf at --quick-sp, freenerf-lite) on MESH (a mesh file or a "
                          "key of SCENES) at the cheapest failing size (bench.sparse_views.QUICK; flags still win), "
                          "printing 'baseline PSNR X, SP PSNR Y, FreeNeRF PSNR Z (object)' last")
    mip.add_argument("--quick-sp", default="1.0@0.333", metavar="ALPHA0@END[:grid]",
                     help="the SP run of --quick (default: the sparse-view setting, alpha0 about the object's radius)")
    mip.add_argument("--up-axis", choices=["x", "y", "z"], help="of the --quick mesh (known meshes: their own)")
    for f in dataclasses.fields(MipBudget):
        flag = "--" + f.name.replace("_", "-")
        if isinstance(f.default, bool):
            mip.add_argument(flag, action="store_true", help=f"(MipBudget.{f.name})")
        elif f.name == "view_selection":
            mip.add_argument(flag, default=f.default, choices=VIEW_SELECTIONS)
        else:
            mip.add_argument(flag, type=type(f.default), default=f.default)
    cost = sub.add_parser("cost", help="SP per-step cost on the ReLU field")
    cost.add_argument("--resolutions", nargs="+", type=int, default=[65, 129])
    cost.add_argument("--rays", type=int, default=1024)
    cost.add_argument("--samples", type=int, default=96)
    cost.add_argument("--color-mode", default="rgb", choices=["rgb", "sh"])
    cost.add_argument("--repeats", type=int, default=30)
    cost.add_argument("--voxels", nargs="+", type=float, default=[0.25, 2.0, 8.0], help="alpha in voxels of the grid")
    cost.add_argument("--end", type=float, default=0.3)
    for p in (relu, mip, cost):
        p.add_argument("--threads", type=int, default=1, help="torch threads (1 on a shared machine)")
        p.add_argument("--overwrite", action="store_true", help="recompute runs that already have results")
        p.add_argument("--tag", default="final", help="label of this table (probes use their own)")
    for p in (relu, mip):
        p.add_argument("--seeds", nargs="+", type=int, default=[0])
    args = parser.parse_args(argv)
    if getattr(args, "dtu_like", False) and (args.image, args.test_views) != (MipBudget.image, MipBudget.test_views):
        mip.error("--image and --test-views do not apply with --dtu-like (its scene has 3 test views of 96x72); drop them")
    if getattr(args, "paper_regime", False):
        relu.set_defaults(**PAPER_REGIME)
        args = parser.parse_args(argv)
    if getattr(args, "quick", None):
        from bench.sparse_views import QUICK

        mip.set_defaults(**QUICK)
        args = parser.parse_args(argv)
    start(args.threads, quiet=("nerfstudio", "PIL", "sp_plugins"))
    rd.OUT.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    if args.study == "relu":
        budget = ReLUBudget(**{f.name: getattr(args, f.name) for f in dataclasses.fields(ReLUBudget)})
        budget.density_init = tuple(budget.density_init)  # type: ignore[assignment]
        for scene in args.scenes:
            for seed in args.seeds:
                relu_study(scene, budget, args.sp, args.methods, seed, args.tag, args.overwrite, args.save_grids)
        text = relu_table(collect("relu", args.tag))
    elif args.study == "mipnerf" and args.quick:
        from bench import sparse_views

        budget = MipBudget(**{f.name: getattr(args, f.name) for f in dataclasses.fields(MipBudget)})
        line = sparse_views.quick(args.quick, budget, args.seeds[0], args.tag if args.tag != "final" else "quick",
                                  sparse_views.SPSetting.parse(args.quick_sp), args.up_axis, args.overwrite)
        print(f"wall time {time.time() - t0:.0f} s; results in {sparse_views.out_dir()}")
        print(line)
        return
    elif args.study == "mipnerf":
        budget = MipBudget(**{f.name: getattr(args, f.name) for f in dataclasses.fields(MipBudget)})
        for scene in args.scenes:
            for seed in args.seeds:
                mip_study(scene, budget, seed, args.tag, args.overwrite)
        text = mip_table(collect("mipnerf", args.tag))
    else:
        results = [cost_study(r, args.rays, args.samples, args.color_mode, args.repeats, v, args.end)
                   for r in args.resolutions for v in args.voxels]
        (rd.OUT / f"cost_{args.tag}.json").write_text(json.dumps(results, indent=1))
        text = table(["grid", "alpha", "s/step plain", "SP total", "SP arithmetic", "slower lookups", "alpha = 0", "averaged over the schedule"],
                     [(f"{r['resolution']}^3 {r['color_mode']}", f"{r['alpha_voxels']:g} vox", f"{s['plain']['median_s']:.3f}",
                       f"{r['sp_total_ratio']:.3f}", f"+{100 * r['sp_arithmetic_share']:.1f}%", f"+{100 * r['lookup_slowdown_share']:.1f}%",
                       f"{s['sp_inactive']['ratio_vs_plain']:.3f}", f"{r['schedule_average_ratio']:.3f} (end {r['end']})")
                      for r in results for s in [r["summary"]]])
    (rd.OUT / f"{args.study}_{args.tag}.md").write_text(text + "\n")
    print(text)
    print(f"\nwall time {time.time() - t0:.0f} s; machine: {machine_info()}")


if __name__ == "__main__":
    main()
