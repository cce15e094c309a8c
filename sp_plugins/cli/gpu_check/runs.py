"""Part ``runs``: nerfstudio methods trained in this process on a small synthetic scene, ours and the
host's: steady-state seconds per step (CUDA events after warm-up steps), peak memory, and the
host-device syncs per step, ours and the host's."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import gc
import statistics
import time
from pathlib import Path
from typing import List, Optional

import torch

from sp_plugins.adapter.shrink import shrink
from sp_plugins.cli.gpu_check.budget import Deadline, Sizes
from sp_plugins.cli.gpu_check.machine import tcnn_reason
from sp_plugins.cli.gpu_check.measure import Memory, count_syncs, time_steps
from sp_plugins.cli.gpu_check.report import failure, log
from sp_plugins.data import make_tiny_scene
from sp_plugins.encodings import HashGrid
from sp_plugins.encodings.hashgrid import torch_backend_only
from sp_plugins.nerfstudio import table
from sp_plugins.nerfstudio.components.lpips import offline_lpips
from sp_plugins.nerfstudio.registration import sp_methods
from sp_plugins.nerfstudio.runs import configure_run, method_config

SDF_BASELINE = table.HASH_GRID_SDF
SDF_SP = table.OUR_BASELINES[SDF_BASELINE]
"""The SDF pair the check times: our hash-grid NeuS and the SP method the nerfstudio table pairs it with."""
CHECKPOINT_RUN = SDF_SP
"""The run whose checkpoint the ``checkpoint`` part reads."""

RUNS = (
    # name, method, how, note
    (SDF_BASELINE, SDF_BASELINE, "ours", f"baseline of {SDF_SP}"),
    (SDF_SP, SDF_SP, "ours", ""),
    (f"{SDF_SP} (torch grid)", SDF_SP, "ours-torch", "our torch hash grid on the GPU"),
    (table.NERFACTO, table.NERFACTO, "host", f"nerfstudio's own, the baseline of sp-train {table.NERFACTO}"),
    (f"sp-train {table.NERFACTO}", table.NERFACTO, "sp-train", ""),
    (table.SP_NERFACTO, table.SP_NERFACTO, "ours", ""),
)


QUICK_SDF = dict(num_samples=16, num_samples_importance=8, num_up_sample_steps=1, background_model="none",
                 eval_num_rays_per_chunk=256)
QUICK_SDF_FIELD = dict(hidden_dim=32, num_layers=2, hidden_dim_color=32, geo_feat_dim=15, num_levels=8, max_res=64,
                       log2_hashmap_size=12)
QUICK_NERFACTO = dict(num_nerf_samples_per_ray=8, num_proposal_samples_per_ray=(8, 8), log2_hashmap_size=12, max_res=64,
                      hidden_dim=16, hidden_dim_color=16, eval_num_rays_per_chunk=256)
QUICK_PROPOSAL_NET = dict(log2_hashmap_size=10, max_res=32, hidden_dim=8)


def shrink_for_quick(config) -> None:
    """CPU-sized models for ``--quick`` (the SDF methods and the nerfacto family of :data:`RUNS`):
    small MLPs, grids and sample counts, nerfacto's camera optimizer off."""
    model = config.pipeline.model
    if hasattr(model, "sdf_field"):
        shrink(config, **QUICK_SDF, field=QUICK_SDF_FIELD)
        return
    shrink(config, **QUICK_NERFACTO, proposal_net_args_list=[{**args, **QUICK_PROPOSAL_NET} for args in model.proposal_net_args_list],
           camera_optimizer=dataclasses.replace(model.camera_optimizer, mode="off"))


def _vanilla_data(config) -> None:
    """nerfstudio's vanilla data manager in place of a parallel one (no worker processes)."""
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
    from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManagerConfig

    dm = config.pipeline.datamanager
    if isinstance(dm, ParallelDataManagerConfig):
        names = [f.name for f in dataclasses.fields(VanillaDataManagerConfig) if f.init and f.name != "_target"]
        config.pipeline.datamanager = VanillaDataManagerConfig(**{n: getattr(dm, n) for n in names})


def run_config(method: str, how: str, scene: Path, out: Path, device, sizes: Sizes):
    """The trainer config of one of :data:`RUNS` (``how``: ``ours``, ``host`` or ``sp-train``) on ``scene``."""
    if how == "host" or how == "sp-train":
        from nerfstudio.configs.method_configs import all_descriptions, all_methods

        if how == "host":
            config = copy.deepcopy(all_methods[method])
        else:
            configs, _, refused = sp_methods({method: all_methods[method]}, all_descriptions)
            if method not in configs:
                raise RuntimeError(f"sp-train refuses {method}: {refused.get(method)}")
            config = copy.deepcopy(configs[method])
        _vanilla_data(config)
    else:
        config = method_config(method)
    if sizes.quick:
        shrink_for_quick(config)
    configure_run(config, scene / "blender", steps=10**6, output_dir=out, layout="blender", device=device.type,
                  rays_per_batch=sizes.rays, experiment_name=out.name)
    return config


def train_in_process(config, device, torch_grid: bool = False):
    """A set-up nerfstudio trainer, and ``step(i)``: one training iteration with its callbacks;
    ``torch_grid``: every ``auto`` hash grid takes our torch backend, also where tcnn runs."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    config.save_config()
    with _grids(torch_grid), offline_lpips():
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
    losses: list = []

    def step(i: int) -> None:
        with _grids(torch_grid):
            trainer.pipeline.train()
            for callback in trainer.callbacks:
                callback.run_callback_at_location(i, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            loss, _, _ = trainer.train_iteration(i)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(i, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
            losses.append(loss.detach())

    return trainer, step, losses


def _grids(torch_grid: bool):
    return torch_backend_only() if torch_grid else contextlib.nullcontext()


def grid_backends(module) -> List[str]:
    return sorted({m.backend for m in module.modules() if isinstance(m, HashGrid)}) or ["host's own"]


def time_run(name: str, method: str, how: str, scene: Path, out: Path, device, sizes: Sizes, artifacts: dict) -> dict:
    """One of :data:`RUNS` trained in this process: seconds per step, memory, syncs; the
    :data:`CHECKPOINT_RUN`'s checkpoint goes to ``artifacts`` for the checkpoint part."""
    torch_grid = how == "ours-torch"
    config = run_config(method, "ours" if torch_grid else how, scene, out, device, sizes)
    with Memory(device) as memory:
        start = time.perf_counter()
        trainer, step, losses = train_in_process(config, device, torch_grid)
        setup_s = time.perf_counter() - start
        for i in range(sizes.warmup):
            step(i)
        times = time_steps(step, sizes.warmup, sizes.timed, device)
    last = sizes.warmup + sizes.timed
    syncs = count_syncs(step, last, sizes.counted, device)
    last += sizes.counted
    model = trainer.pipeline.model
    sp = getattr(model, "sp", None)
    finite = bool(torch.isfinite(torch.stack([loss.float() for loss in losses])).all())
    result = {
        "method": method, "route": how, "setup_s": setup_s, "steps_timed": sizes.timed,
        "seconds_per_step": statistics.median(times), "seconds_per_step_mean": statistics.fmean(times),
        "memory": memory.result, "syncs": syncs, "hash_grid": grid_backends(model), "finite": finite,
        "mixed_precision": bool(trainer.mixed_precision), "sp_alpha": float(getattr(sp, "alpha", 0.0)) if sp is not None else None,
        "rays_per_batch": config.pipeline.datamanager.train_num_rays_per_batch,
    }
    if name == CHECKPOINT_RUN:
        trainer.save_checkpoint(last - 1)
        artifacts["checkpoint"] = {"config": config, "dir": trainer.checkpoint_dir, "step": last - 1,
                                   "backend": result["hash_grid"][0]}
    del trainer, step, losses
    if device.type == "cuda":  # the next run's memory starts from what it allocates itself
        gc.collect()
        torch.cuda.empty_cache()
    return result


def check_runs(device, sizes: Sizes, out: Path, deadline: Deadline, artifacts: dict) -> dict:
    """Part ``runs``: :data:`RUNS` on a small synthetic scene, the SP overhead per step and torch
    vs tcnn from them; a syncing, non-finite or SP-off run is a problem."""
    try:
        import nerfstudio  # noqa: F401
    except ImportError:
        return {"status": "skipped", "reason": "nerfstudio is not installed (pip install 'sp-plugins[nerfstudio]')"}
    if device.type == "cuda" and device.index not in (None, 0):
        return {"status": "skipped", "reason": f"nerfstudio trains on cuda:0 (local rank 0); pick the GPU with "
                                               f"CUDA_VISIBLE_DEVICES={device.index} and --device cuda"}
    scene = make_tiny_scene(out / "scene", mesh="sphere", overwrite=True, **sizes.scene).root
    result: dict = {"runs": {}, "skipped": [], "scene": str(scene)}
    per_run = 25.0 if sizes.quick else 40.0
    for name, method, how, note in RUNS:
        if how == "ours-torch" and tcnn_reason(device) is not None:
            result["skipped"].append(f"{name}: {SDF_SP} already runs the torch grid here ({tcnn_reason(device)})")
            continue
        late = deadline.too_late(per_run + 60)  # leave time for the later parts
        if late:
            result["skipped"].append(f"{name}: {late}")
            continue
        log(f"runs: {name} ...")
        try:
            result["runs"][name] = dict(time_run(name, method, how, scene, out / name.replace(" ", "_"), device, sizes, artifacts), note=note)
        except Exception as exc:  # a broken run is a finding: record it, run the others
            result["runs"][name] = {"status": "failed", "error": failure(exc)}
    runs = result["runs"]

    def ratio(a: str, b: str) -> Optional[dict]:
        if "seconds_per_step" in runs.get(a, {}) and "seconds_per_step" in runs.get(b, {}):
            same = runs[a]["hash_grid"] == runs[b]["hash_grid"]
            return {"ratio": runs[a]["seconds_per_step"] / runs[b]["seconds_per_step"], "grids": [runs[a]["hash_grid"], runs[b]["hash_grid"]],
                    "comparable": same}
        return None

    result["sp_overhead"] = {k: v for k, v in ((SDF_BASELINE, ratio(SDF_SP, SDF_BASELINE)),
                                               (table.NERFACTO, ratio(f"sp-train {table.NERFACTO}", table.NERFACTO))) if v}
    if ratio(f"{SDF_SP} (torch grid)", SDF_SP):
        result["torch_over_tcnn"] = ratio(f"{SDF_SP} (torch grid)", SDF_SP)
    if device.type != "cuda":
        result["skipped"].append("memory and CUDA sync debug mode: CUDA only")
    problems = [f"{n}: {r.get('error') or 'not finite' if not r.get('finite', False) else ''}" for n, r in runs.items()
                if "error" in r or not r.get("finite", False)]
    problems += [f"{n}: {r['syncs']['ours_per_step']:g} syncs of ours per step at {sorted(r['syncs']['ours'])}"
                 for n, r in runs.items() if r.get("syncs", {}).get("ours")]
    problems += [f"{n}: SP off (alpha {r['sp_alpha']})" for n, r in runs.items()
                 if n.startswith("sp-") and r.get("sp_alpha") is not None and not r["sp_alpha"] > 0]
    result["problems"] = problems
    cut = any("deadline" in s for s in result["skipped"])
    result["status"] = "failed" if problems or cut else "ok"
    return result
