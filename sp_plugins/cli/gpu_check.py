"""sp-gpu-check: the first thing to run on a machine with an NVIDIA GPU (8 minutes at most).

    sp-gpu-check                          # CUDA; writes gpu-check/gpu_check.json, exit 1 if anything failed
    sp-gpu-check --require-tcnn           # a missing tinycudann is a failure too
    sp-gpu-check --device cpu --quick     # the parts a CPU can run, small (what the tests run)

It checks what no CPU test can see, each part reporting what it skipped and why:

- ``grid``: tiny-cuda-nn's hash grid against our torch backend from the same weights: outputs and
  input gradients judged by the fraction of points over a relative tolerance (one point the two
  floor into different cells does not fail it), table gradients (tcnn accumulates them in half
  precision), the round trip of the weights, fit and eikonal step times; our grid and SP under
  ``torch.autocast`` (fp16 on CUDA, bf16 on a CPU): positions stay float32 and move. Without
  tinycudann the comparison runs against :mod:`sp_plugins.encodings.tcnn_layout` (tcnn's layout
  read independently) and says so.
- ``runs``: ``neus-hashgrid``, ``sp-neus-hashgrid``, ``sp-neus-hashgrid`` on the torch backend,
  nerfstudio's ``nerfacto``, ``sp-train nerfacto`` and ``sp-nerfacto`` (mixed precision on CUDA as
  configured) trained in this process on a small synthetic scene: steady-state seconds per step
  (CUDA events, after warm-up steps), peak memory from the allocator and the device, and host-device
  syncs per step, ours and the host's (:mod:`sp_plugins.sync_count`, and on CUDA
  ``torch.cuda.set_sync_debug_mode``). From them: the SP overhead per step and torch vs tcnn.
- ``checkpoint``: the ``sp-neus-hashgrid`` checkpoint resumed under the other hash-grid backend
  (weights and Adam moments) and evaluated by ``ns-eval`` with CUDA hidden.
- ``fit``: ``sp-fit pointcloud``'s trainer on the device: seconds per step from its timer against
  the wall clock, no sync of ours per step.

The whole check stops at ``--deadline`` seconds (default 480) counted from the process start;
parts that no longer fit are skipped, naming the deadline, and a part still running then is
reported as cut. A CUDA build of torch that sees no GPU is a failure (exit 1, with the driver and
``torch.version.cuda``), not a skip. Attach ``gpu_check.json`` to GPU bug reports.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

PARTS = ("grid", "runs", "checkpoint", "fit")
DEADLINE_S = 480.0
GRID_SETTING = dict(num_levels=16, features_per_level=2, log2_hashmap_size=19, base_resolution=16, max_resolution=2048)
CPU_COMMAND = "sp-gpu-check --device cpu --quick"  # what a machine without a GPU can run: named by every no-GPU error
QUICK_GRID = dict(num_levels=4, features_per_level=2, log2_hashmap_size=10, base_resolution=4, max_resolution=64)


def process_age() -> float:
    """Seconds since this process started (its start-up counts against the deadline)."""
    try:
        import psutil

        return max(time.time() - psutil.Process().create_time(), 0.0)
    except Exception:  # no psutil: from /proc, else nothing known
        try:
            ticks = os.sysconf("SC_CLK_TCK")
            start = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19]) / ticks
            return max(float(Path("/proc/uptime").read_text().split()[0]) - start, 0.0)
        except Exception:
            return 0.0


class Deadline:
    """The global deadline: what is left, and whether a part of a given length still fits."""

    def __init__(self, seconds: float, since_process_start: bool = True) -> None:
        self.seconds = seconds
        self.start = time.monotonic() - (process_age() if since_process_start else 0.0)

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def remaining(self) -> float:
        return self.seconds - self.elapsed()

    def too_late(self, needs: float) -> Optional[str]:
        left = self.remaining()
        if left < needs:
            return f"deadline: {left:.0f} s of --deadline {self.seconds:.0f} s left, this needs about {needs:.0f} s"
        return None


class Sizes:
    """How big each part is: real sizes on a GPU, tiny with ``--quick``."""

    def __init__(self, quick: bool) -> None:
        self.quick = quick
        self.grid = QUICK_GRID if quick else GRID_SETTING
        self.grid_points = 2**12 if quick else 2**18
        self.grid_repeats = 2 if quick else 20
        self.warmup, self.timed, self.counted = (1, 2, 1) if quick else (10, 30, 2)
        self.rays = 64 if quick else None  # None: the method's own batch
        self.scene = dict(n_train=8, n_val=2, n_test=2, resolution=32) if quick else dict(n_train=24, n_val=2, n_test=2, resolution=64)
        self.resume_steps = 2 if quick else 5
        self.fit_steps = 4 if quick else 200
        self.eval_on_cpu = not quick


# ------------------------------------------------------------------------------------------------
# the machine


def nvidia_driver() -> Optional[str]:
    """``name, driver`` per GPU from ``nvidia-smi`` (None when it is not installed)."""
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return None
    try:
        proc = subprocess.run([exe, "--query-gpu=name,driver_version", "--format=csv,noheader"], capture_output=True,
                              text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"nvidia-smi failed: {exc}"
    return (proc.stdout.strip() or proc.stderr.strip() or f"nvidia-smi exit {proc.returncode}").replace("\n", "; ")


def cuda_problem(device: str) -> Optional[str]:
    """Why ``device`` (a CUDA device) cannot be checked here, in one line; None when it can."""
    import torch

    if torch.version.cuda is None:
        return (f"torch {torch.__version__} is a CPU-only build: no GPU can be checked; install a CUDA build of torch, "
                f"or check the CPU paths only: {CPU_COMMAND}")
    driver = nvidia_driver()
    seen = f"NVIDIA driver: {driver}" if driver else "nvidia-smi not found (no NVIDIA driver installed?)"
    if not torch.cuda.is_available():
        return (f"torch {torch.__version__} is a CUDA {torch.version.cuda} build but sees no CUDA device ({seen}); an NVIDIA "
                f"driver too old for CUDA {torch.version.cuda} hides the GPU from it: update the driver, or install a torch "
                f"build for the driver's CUDA version; on a machine without a GPU, check the CPU paths: {CPU_COMMAND}")
    dev = torch.device(device)
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        return f"--device {device}: this machine has {torch.cuda.device_count()} CUDA device(s) ({seen})"
    return None


def machine_report(device) -> dict:
    import torch

    info = {"python": platform.python_version(), "torch": torch.__version__, "torch_cuda": torch.version.cuda,
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "device": str(device), "nvidia_smi": nvidia_driver()}
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        info.update(gpu=props.name, gpu_memory_gib=round(props.total_memory / 2**30, 1), capability=f"{props.major}.{props.minor}")
    try:
        from importlib.metadata import version

        info["tinycudann"] = version("tinycudann")
    except Exception:  # not installed, or installed without metadata
        info["tinycudann"] = None
    for name in ("nerfstudio", "sp-plugins"):
        try:
            from importlib.metadata import version

            info[name] = version(name)
        except Exception:
            info[name] = None
    return info


def tcnn_reason(device) -> Optional[str]:
    """Why tiny-cuda-nn cannot run on ``device`` (None when it can)."""
    from sp_plugins.encodings.hashgrid import _import_tcnn

    if device.type != "cuda":
        return f"tiny-cuda-nn runs on CUDA only (--device {device})"
    if _import_tcnn() is None:
        return "tinycudann does not import (see the README's tiny-cuda-nn install line)"
    return None


# ------------------------------------------------------------------------------------------------
# timing, memory, syncs


def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_steps(step: Callable[[int], Any], first: int, count: int, device) -> List[float]:
    """Seconds of each of ``count`` steps: CUDA events on CUDA (queued work included, no sync
    between steps), the wall clock elsewhere."""
    import torch

    if device.type != "cuda":
        times = []
        for i in range(count):
            start = time.perf_counter()
            step(first + i)
            times.append(time.perf_counter() - start)
        return times
    events = [(torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)) for _ in range(count)]
    for i, (start, end) in enumerate(events):
        start.record()
        step(first + i)
        end.record()
    torch.cuda.synchronize(device)
    return [start.elapsed_time(end) / 1000.0 for start, end in events]


@contextlib.contextmanager
def gpu_code_paths(device):
    """On a CPU, the branches a GPU run takes while syncs are counted: the reflect boundary's dense
    fold (the CPU's sparse fold reads a count back on purpose, cheap there)."""
    import sp_plugins.core.boundary as boundary

    if device.type == "cuda":
        yield
        return
    saved = boundary.sparse_fold_on
    boundary.sparse_fold_on = lambda device: False
    try:
        yield
    finally:
        boundary.sparse_fold_on = saved


def count_syncs(step: Callable[[int], Any], first: int, count: int, device) -> dict:
    """Stalling ops per step over ``count`` steps, ours and the host's by site (on a CPU along the
    GPU's branches, :func:`gpu_code_paths`); on CUDA also what ``torch.cuda.set_sync_debug_mode``
    reports (the syncs that really happened)."""
    import torch

    from sp_plugins.sync_count import SyncCounter, site_of

    records: list = []
    counter = SyncCounter(devices={"cuda"} if device.type == "cuda" else None, skip_files=[__file__])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if device.type == "cuda":
            torch.cuda.set_sync_debug_mode("warn")
        try:
            with gpu_code_paths(device), counter:
                for i in range(count):
                    step(first + i)
        finally:
            if device.type == "cuda":
                torch.cuda.set_sync_debug_mode(0)
        records = [w for w in caught if "synchroniz" in str(w.message)]
    ours = counter.ours()
    result = {
        "steps": count,
        "ours_per_step": sum(ours.values()) / count,
        "host_per_step": (sum(counter.counts.values()) - sum(ours.values())) / count,
        "ours": {site: n / count for site, n in ours.items()},
        "host": {site: n / count for site, n in counter.counts.items() if site not in ours},
    }
    if device.type == "cuda":
        sites: Dict[str, float] = {}
        for w in records:
            site, _ = site_of(w.filename, w.lineno)
            sites[site] = sites.get(site, 0) + 1 / count
        result["cuda_sync_debug"] = {"per_step": len(records) / count, "sites": sites}
    return result


class Memory:
    """Peak allocator memory and the device's used memory around a block (CUDA only)."""

    def __init__(self, device) -> None:
        self.device = device
        self.result: dict = {}

    def __enter__(self) -> "Memory":
        import torch

        if self.device.type == "cuda":
            _sync(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.start = torch.cuda.memory_allocated(self.device)
            free, total = torch.cuda.mem_get_info(self.device)
            self.device_start = total - free
        return self

    def __exit__(self, *exc) -> None:
        import torch

        if self.device.type == "cuda":
            _sync(self.device)
            free, total = torch.cuda.mem_get_info(self.device)
            self.result = {
                "allocator_peak_mib": torch.cuda.max_memory_allocated(self.device) / 2**20,
                "allocator_peak_over_start_mib": (torch.cuda.max_memory_allocated(self.device) - self.start) / 2**20,
                "reserved_peak_mib": torch.cuda.max_memory_reserved(self.device) / 2**20,
                "device_used_growth_mib": (total - free - self.device_start) / 2**20,  # tcnn's own allocations land here too
            }


# ------------------------------------------------------------------------------------------------
# part: the hash grid


def compare_points(reference, candidate, tolerance: float, max_bad_fraction: float) -> dict:
    """Per-point agreement of ``[N, ...]`` tensors: the relative error of each point (its row's
    norm, against the reference's, with a floor of a tenth of the median norm) and the fraction of
    points over ``tolerance``: one point floored into another cell by a rounding does not fail it."""
    a = reference.detach().float().reshape(reference.shape[0], -1)
    b = candidate.detach().float().reshape(candidate.shape[0], -1)
    norm = a.norm(dim=1)
    floor = max(float(norm.median()) * 0.1, 1e-12)
    err = (a - b).norm(dim=1) / (norm + floor)
    bad = float((err > tolerance).float().mean())
    return {"fraction_over_tolerance": bad, "median_relative": float(err.median()), "max_relative": float(err.max()),
            "tolerance": tolerance, "max_fraction": max_bad_fraction, "ok": bad <= max_bad_fraction and bool(err.isfinite().all())}


def compare_tables(reference, candidate, tolerance: float) -> dict:
    """Table gradients as whole vectors: relative L2 difference and cosine."""
    import torch

    a, b = reference.detach().float().reshape(-1), candidate.detach().float().reshape(-1)
    rel = float((a - b).norm() / a.norm().clamp_min(1e-30))
    cos = float(torch.nn.functional.cosine_similarity(a, b, dim=0))
    return {"relative_l2": rel, "cosine": cos, "tolerance": tolerance, "ok": rel <= tolerance and math.isfinite(rel)}


def agreement(reference, candidate, x, tolerance: float = 1e-2, max_bad_fraction: float = 1e-2, table_tolerance: float = 5e-2) -> dict:
    """Outputs, input gradients and table gradients of two grids holding the same weights, at ``x``."""
    import torch

    x = x.detach().requires_grad_(True)
    outputs, grads, tables = [], [], []
    for grid in (reference, candidate):
        param = next(grid.parameters())
        param.grad = None
        out = grid(x)
        w = torch.linspace(-1.0, 1.0, out.shape[-1], device=x.device)
        (g,) = torch.autograd.grad((out.float() * w).sum(), x, retain_graph=True)
        (out.float() * w).sum().backward()
        outputs.append(out.detach())
        grads.append(g)
        tables.append(param.grad.detach().reshape(-1).clone())
    result = {
        "points": x.shape[0],
        "output_dtype": str(outputs[1].dtype),
        "output": compare_points(outputs[0], outputs[1], tolerance, max_bad_fraction),
        "input_gradient": compare_points(grads[0], grads[1], tolerance, max_bad_fraction),
        "table_gradient": compare_tables(tables[0], tables[1], table_tolerance),
    }
    result["ok"] = all(result[k]["ok"] for k in ("output", "input_gradient", "table_gradient"))
    return result


def grid_step_fns(grid, points: int, device) -> Dict[str, Callable[[int], None]]:
    """A fit step (backward into the table) and an eikonal step (double backward), with a small MLP."""
    import torch

    mlp = torch.nn.Sequential(torch.nn.Linear(grid.n_output_dims, 64), torch.nn.Softplus(beta=100), torch.nn.Linear(64, 1)).to(device)

    def fit(_: int) -> None:
        x = torch.rand(points, 3, device=device)
        mlp(grid(x).float()).square().mean().backward()

    def eikonal(_: int) -> None:
        x = torch.rand(points, 3, device=device, requires_grad=True)
        f = mlp(grid(x).float())
        (g,) = torch.autograd.grad(f.sum(), x, create_graph=True)
        ((g.norm(dim=-1) - 1).square().mean() + f.square().mean()).backward()

    return {"fit": fit, "eikonal": eikonal}


def autocast_check(device, grid) -> dict:
    """Our grid and SP under ``torch.autocast`` (fp16 on CUDA, bf16 elsewhere): the grid agrees with
    float32, and half positions in [0.5, 1] moved by alpha 1e-4 come back float32 and moved."""
    import torch

    from sp_plugins.core import perturb

    dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    x = torch.rand(4096, 3, device=device)
    with torch.no_grad():
        plain = grid(x)
        with torch.autocast(device.type, dtype=dtype):
            cast = grid(x)
    half = (torch.rand(100_000, 3, device=device) * 0.5 + 0.5).to(dtype)
    with torch.autocast(device.type, dtype=dtype):
        moved = perturb(half, 1e-4, generator=torch.Generator(device=device).manual_seed(0))
    fraction = float((moved != half.to(moved.dtype)).float().mean())
    result = {"dtype": str(dtype), "grid": compare_points(plain, cast, 1e-2, 1e-2), "grid_output_dtype": str(cast.dtype),
              "sp_positions_dtype": str(moved.dtype), "sp_moved_fraction": fraction}
    result["ok"] = result["grid"]["ok"] and moved.dtype in (torch.float32, torch.float64) and fraction >= 0.999
    return result


def check_grid(device, sizes: Sizes, args, deadline: Deadline) -> dict:
    import torch

    from sp_plugins.encodings import HashGrid
    from sp_plugins.encodings.tcnn_layout import TcnnLayoutEncoding

    result: dict = {"setting": sizes.grid, "skipped": []}
    torch.manual_seed(0)
    reference = HashGrid(**sizes.grid, backend="torch", init_scale=1.0).to(device)
    x = torch.rand(min(sizes.grid_points, 2**16), 3, device=device)
    reason = tcnn_reason(device)
    if reason is None:
        with torch.cuda.device(device):
            candidate = HashGrid(**sizes.grid, backend="tcnn")
        candidate.load_state_dict(reference.state_dict())  # the checkpoint mapping, torch -> tcnn
        result["against"] = "tinycudann"
        back = HashGrid(**sizes.grid, backend="torch").to(device)
        back.load_state_dict(candidate.state_dict())
        result["round_trip_identical"] = bool(torch.equal(back.table, reference.table))
    else:
        result["skipped"].append(f"tcnn: {reason}")
        # tcnn's layout read independently (one level and one corner at a time): checks the comparison itself
        candidate = TcnnLayoutEncoding(3, reference.tcnn_config()).to(device)
        with torch.no_grad():
            candidate.params.copy_(reference.table)
        result["against"] = "tcnn_layout stand-in (not tcnn)"
        x = x[:4096]
    result["agreement"] = agreement(reference, candidate, x, args.tolerance, args.max_bad_fraction, args.table_tolerance)
    result["autocast"] = autocast_check(device, reference)
    if device.type == "cuda" and reason is None and not deadline.too_late(30):
        speed: dict = {}
        for name, grid in (("torch", reference), ("tcnn", candidate)):
            for kind, step in grid_step_fns(grid, sizes.grid_points, device).items():
                try:  # e.g. a tcnn build without double backward fails the eikonal step: keep the rest
                    step(0)
                    times = time_steps(step, 0, sizes.grid_repeats, device)
                    speed.setdefault(name, {})[kind] = statistics.median(times)
                except Exception as exc:
                    speed.setdefault(name, {})[kind] = {"error": f"{type(exc).__name__}: {exc}"}
        for kind in ("fit", "eikonal"):
            a, b = speed.get("torch", {}).get(kind), speed.get("tcnn", {}).get(kind)
            if isinstance(a, float) and isinstance(b, float):
                speed[f"{kind}_torch_over_tcnn"] = a / b
        result["seconds_per_step"] = speed
        errors = [k for v in speed.values() if isinstance(v, dict) for k, e in v.items() if isinstance(e, dict)]
    else:
        result["skipped"].append("speed: " + ("timed against tcnn on CUDA only" if device.type != "cuda" or reason else "deadline"))
        errors = []
    ok = result["agreement"]["ok"] and result["autocast"]["ok"] and result.get("round_trip_identical", True) and not errors
    if reason is not None and args.require_tcnn:
        result["error"] = f"--require-tcnn: {reason}"
        ok = False
    result["status"] = "ok" if ok else "failed"
    return result


# ------------------------------------------------------------------------------------------------
# part: nerfstudio runs

RUNS = (
    # name, method, how, note
    ("neus-hashgrid", "neus-hashgrid", "ours", "baseline of sp-neus-hashgrid"),
    ("sp-neus-hashgrid", "sp-neus-hashgrid", "ours", ""),
    ("sp-neus-hashgrid (torch grid)", "sp-neus-hashgrid", "ours-torch", "our torch hash grid on the GPU"),
    ("nerfacto", "nerfacto", "host", "nerfstudio's own, the baseline of sp-train nerfacto"),
    ("sp-train nerfacto", "nerfacto", "sp-train", ""),
    ("sp-nerfacto", "sp-nerfacto", "ours", ""),
)


@contextlib.contextmanager
def grid_backend(choice: Optional[str]):
    """Within the block, ``backend="auto"`` hash grids resolve to ``choice``: ``torch`` (tcnn's
    devices emptied: our torch grid on the GPU); None leaves them as they are."""
    from sp_plugins.encodings import hashgrid as module

    if choice is None:
        yield
        return
    saved = module.TCNN_DEVICE_TYPES
    module.TCNN_DEVICE_TYPES = ()
    try:
        yield
    finally:
        module.TCNN_DEVICE_TYPES = saved


def _shrink(model) -> None:
    """CPU-sized models for --quick: small MLPs, grids and sample counts."""
    small = dict(num_nerf_samples_per_ray=8, num_proposal_samples_per_ray=(8, 8), log2_hashmap_size=12, max_res=64,
                 hidden_dim=16, hidden_dim_color=16, eval_num_rays_per_chunk=256)
    for key, value in small.items():
        if hasattr(model, key):
            setattr(model, key, value)
    if getattr(model, "camera_optimizer", None) is not None:
        model.camera_optimizer.mode = "off"
    if hasattr(model, "proposal_net_args_list"):
        for args in model.proposal_net_args_list:
            args.update(log2_hashmap_size=10, max_res=32, hidden_dim=8)
    field = getattr(model, "sdf_field", None)
    if field is not None:
        for key, value in dict(hidden_dim=32, num_layers=2, hidden_dim_color=32, geo_feat_dim=15, num_levels=8, max_res=64,
                               log2_hashmap_size=12).items():
            setattr(field, key, value)
        for key, value in dict(num_samples=16, num_samples_importance=8, num_up_sample_steps=1, background_model="none").items():
            setattr(model, key, value)


def _vanilla_data(config) -> None:
    """nerfstudio's vanilla data manager in place of a parallel one (no worker processes)."""
    import dataclasses

    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
    from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManagerConfig

    dm = config.pipeline.datamanager
    if isinstance(dm, ParallelDataManagerConfig):
        names = [f.name for f in dataclasses.fields(VanillaDataManagerConfig) if f.init and f.name != "_target"]
        config.pipeline.datamanager = VanillaDataManagerConfig(**{n: getattr(dm, n) for n in names})


def run_config(method: str, how: str, scene: Path, out: Path, device, sizes: Sizes):
    from sp_plugins.nerfstudio.runs import configure_run, method_config

    if how == "host" or how == "sp-train":
        from nerfstudio.configs.method_configs import all_descriptions, all_methods

        if how == "host":
            config = copy.deepcopy(all_methods[method])
        else:
            from sp_plugins.nerfstudio.registration import sp_methods

            configs, _, refused = sp_methods({method: all_methods[method]}, all_descriptions)
            if method not in configs:
                raise RuntimeError(f"sp-train refuses {method}: {refused.get(method)}")
            config = copy.deepcopy(configs[method])
        _vanilla_data(config)
    else:
        config = method_config(method)
    if sizes.quick:
        _shrink(config.pipeline.model)
    configure_run(config, scene / "blender", steps=10**6, output_dir=out, layout="blender", device=device.type,
                  rays_per_batch=sizes.rays, experiment_name=out.name)
    return config


def train_in_process(config, device, backend: Optional[str] = None):
    """A set-up nerfstudio trainer, and ``step(i)``: one training iteration with its callbacks."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    from sp_plugins.nerfstudio.components.lpips import offline_lpips

    config.save_config()
    with grid_backend(backend), offline_lpips():
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
    losses: list = []

    def step(i: int) -> None:
        with grid_backend(backend):
            trainer.pipeline.train()
            for callback in trainer.callbacks:
                callback.run_callback_at_location(i, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            loss, _, _ = trainer.train_iteration(i)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(i, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
            losses.append(loss.detach())

    return trainer, step, losses


def grid_backends(module) -> List[str]:
    from sp_plugins.encodings import HashGrid

    return sorted({m.backend for m in module.modules() if isinstance(m, HashGrid)}) or ["host's own"]


def time_run(name: str, method: str, how: str, scene: Path, out: Path, device, sizes: Sizes, artifacts: dict) -> dict:
    import torch

    backend = "torch" if how == "ours-torch" else None
    config = run_config(method, "ours" if how == "ours-torch" else how, scene, out, device, sizes)
    with Memory(device) as memory:
        start = time.perf_counter()
        trainer, step, losses = train_in_process(config, device, backend)
        setup_s = time.perf_counter() - start
        for i in range(sizes.warmup):
            step(i)
        times = time_steps(step, sizes.warmup, sizes.timed, device)
    last = sizes.warmup + sizes.timed
    syncs = count_syncs(step, last, sizes.counted, device)
    last += sizes.counted
    model = trainer.pipeline.model
    sp = getattr(model, "sp", None)
    finite = bool(torch.isfinite(torch.stack([l.float() for l in losses])).all())
    result = {
        "method": method, "route": how, "setup_s": setup_s, "steps_timed": sizes.timed,
        "seconds_per_step": statistics.median(times), "seconds_per_step_mean": statistics.fmean(times),
        "memory": memory.result, "syncs": syncs, "hash_grid": grid_backends(model), "finite": finite,
        "mixed_precision": bool(trainer.mixed_precision), "sp_alpha": float(getattr(sp, "alpha", 0.0)) if sp is not None else None,
        "rays_per_batch": config.pipeline.datamanager.train_num_rays_per_batch,
    }
    if name == "sp-neus-hashgrid":
        trainer.save_checkpoint(last - 1)
        artifacts["checkpoint"] = {"config": config, "dir": trainer.checkpoint_dir, "step": last - 1,
                                   "backend": result["hash_grid"][0]}
    del trainer, step, losses
    if device.type == "cuda":  # the next run's memory starts from what it allocates itself
        import gc

        gc.collect()
        torch.cuda.empty_cache()
    return result


def check_runs(device, sizes: Sizes, out: Path, deadline: Deadline, artifacts: dict) -> dict:
    try:
        import nerfstudio  # noqa: F401
    except ImportError:
        return {"status": "skipped", "reason": "nerfstudio is not installed (pip install 'sp-plugins[nerfstudio]')"}
    if device.type == "cuda" and device.index not in (None, 0):
        return {"status": "skipped", "reason": f"nerfstudio trains on cuda:0 (local rank 0); pick the GPU with "
                                               f"CUDA_VISIBLE_DEVICES={device.index} and --device cuda"}
    from sp_plugins.data import make_tiny_scene

    scene = make_tiny_scene(out / "scene", mesh="sphere", overwrite=True, **sizes.scene).root
    result: dict = {"runs": {}, "skipped": [], "scene": str(scene)}
    per_run = 25.0 if sizes.quick else 40.0
    for name, method, how, note in RUNS:
        if how == "ours-torch" and tcnn_reason(device) is not None:
            result["skipped"].append(f"{name}: sp-neus-hashgrid already runs the torch grid here ({tcnn_reason(device)})")
            continue
        late = deadline.too_late(per_run + 60)  # leave time for the later parts
        if late:
            result["skipped"].append(f"{name}: {late}")
            continue
        log(f"runs: {name} ...")
        try:
            result["runs"][name] = dict(time_run(name, method, how, scene, out / name.replace(" ", "_"), device, sizes, artifacts), note=note)
        except Exception as exc:  # a broken run is a finding: record it, run the others
            result["runs"][name] = {"status": "failed", "error": f"{type(exc).__name__}: {first_line(exc)}"}
    runs = result["runs"]

    def ratio(a: str, b: str) -> Optional[dict]:
        if "seconds_per_step" in runs.get(a, {}) and "seconds_per_step" in runs.get(b, {}):
            same = runs[a]["hash_grid"] == runs[b]["hash_grid"]
            return {"ratio": runs[a]["seconds_per_step"] / runs[b]["seconds_per_step"], "grids": [runs[a]["hash_grid"], runs[b]["hash_grid"]],
                    "comparable": same}
        return None

    result["sp_overhead"] = {k: v for k, v in (("neus-hashgrid", ratio("sp-neus-hashgrid", "neus-hashgrid")),
                                               ("nerfacto", ratio("sp-train nerfacto", "nerfacto"))) if v}
    if ratio("sp-neus-hashgrid (torch grid)", "sp-neus-hashgrid"):
        result["torch_over_tcnn"] = ratio("sp-neus-hashgrid (torch grid)", "sp-neus-hashgrid")
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


# ------------------------------------------------------------------------------------------------
# part: the checkpoint on another machine


def check_checkpoint(device, sizes: Sizes, out: Path, deadline: Deadline, artifacts: dict) -> dict:
    import torch

    saved = artifacts.get("checkpoint")
    if saved is None:
        return {"status": "skipped", "reason": "no sp-neus-hashgrid checkpoint: the runs part did not train it (see runs)"}
    result: dict = {"trained_with": saved["backend"], "skipped": []}
    other = "torch" if saved["backend"] == "tcnn" else None
    if other is None:
        result["skipped"].append(f"the other backend: none here ({tcnn_reason(device)}): resumed under the same one")
    late = deadline.too_late(20)
    if late:
        result["skipped"].append(f"resume: {late}")
    else:
        log(f"checkpoint: resume under the {other or saved['backend']} backend ...")
        config = copy.deepcopy(saved["config"])
        config.load_dir = saved["dir"]
        config.output_dir = out / "resumed"
        try:
            trainer, step, losses = train_in_process(config, device, other)
            start = trainer._start_step
            for i in range(start, start + sizes.resume_steps):
                step(i)
            grid = [m for m in trainer.pipeline.model.modules() if type(m).__name__ == "HashGrid"]
            param = next(grid[0].parameters())
            moments = [s.get("exp_avg") for opt in trainer.optimizers.optimizers.values() for p, s in opt.state.items() if p is param]
            result["resume"] = {
                "continued_from_step": start, "backend": grid[0].backend, "other_backend": grid[0].backend != saved["backend"], "finite": bool(torch.isfinite(torch.stack(losses)).all()),
                "adam_moments_match": bool(moments and moments[0] is not None and moments[0].shape == param.shape),
            }
            result["resume"]["ok"] = (result["resume"]["finite"] and result["resume"]["adam_moments_match"]
                                      and start == saved["step"] + 1 and (other is None or result["resume"]["other_backend"]))
        except Exception as exc:
            result["resume"] = {"ok": False, "error": f"{type(exc).__name__}: {first_line(exc)}"}
    if not sizes.eval_on_cpu:
        result["skipped"].append("ns-eval with CUDA hidden: --quick")
    elif deadline.too_late(60):
        result["skipped"].append(f"ns-eval with CUDA hidden: {deadline.too_late(60)}")
    else:
        log("checkpoint: ns-eval with CUDA hidden ...")
        config_path = saved["config"].get_base_dir() / "config.yml"
        metrics = out / "eval_on_cpu.json"
        cmd = [_tool("ns-eval"), "--load-config", str(config_path), "--output-path", str(metrics)]
        env = dict(os.environ, CUDA_VISIBLE_DEVICES="", OMP_WAIT_POLICY="PASSIVE")
        result["eval_on_cpu"] = run_command(cmd, env, timeout=max(deadline.remaining() - 20, 10))
        if metrics.is_file():
            result["eval_on_cpu"]["results"] = json.loads(metrics.read_text()).get("results")
        result["eval_on_cpu"]["ok"] = result["eval_on_cpu"]["returncode"] == 0 and metrics.is_file()
    done = [result[k]["ok"] for k in ("resume", "eval_on_cpu") if k in result]
    cut = any("deadline" in s for s in result["skipped"])
    result["status"] = "ok" if all(done) and not cut else "failed"
    return result


def _tool(name: str) -> str:
    return shutil.which(name) or str(Path(sys.executable).parent / name)


def run_command(cmd: List[str], env: Dict[str, str], timeout: float) -> dict:
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
        code, output = proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as exc:
        code, output = None, f"timed out after {timeout:.0f} s\n{exc.stdout or ''}{exc.stderr or ''}"
    result = {"command": " ".join(cmd), "returncode": code, "seconds": time.perf_counter() - start}
    if code != 0:
        result["output_tail"] = str(output)[-3000:]
    return result


# ------------------------------------------------------------------------------------------------
# part: sp-fit


def check_fit(device, sizes: Sizes, deadline: Deadline) -> dict:
    from importlib.resources import files

    from sp_plugins.geometry import load_oriented_points
    from sp_plugins.tasks import PointCloudSDFConfig
    from sp_plugins.tasks.fields import EncodingConfig

    from sp_plugins.core import SPConfig

    data = load_oriented_points(str(files("sp_plugins.data") / "assets" / "spot.ply"), 50_000, 0)
    sp = SPConfig(alpha0=0.03, schedule="step", end=1.0)  # SP on in every step, the counted ones too
    config = PointCloudSDFConfig(steps=sizes.fit_steps + 3, sp=sp)
    if sizes.quick:
        config = PointCloudSDFConfig(steps=sizes.fit_steps + 3, surface_batch=256, space_batch=256, hidden=(16,), sp=sp,
                                     encoding=EncodingConfig(levels=4, log2_table_size=12, base_resolution=8, max_resolution=64))
    trainer = config.setup(data, device=device)
    trainer.step()  # warm-up
    _sync(device)
    start = time.perf_counter()
    for _ in range(sizes.fit_steps - 1):
        trainer.step()
    _sync(device)
    wall = (time.perf_counter() - start) / max(sizes.fit_steps - 1, 1)
    syncs = count_syncs(lambda i: trainer.step(), 0, 2, device)
    times = trainer.timer.times[1 : sizes.fit_steps]
    result = {"steps": sizes.fit_steps, "seconds_per_step_timer": statistics.fmean(times), "seconds_per_step_wall": wall,
              "timer_over_wall": statistics.fmean(times) / wall if wall > 0 else None, "syncs": syncs,
              "final_loss": trainer.history["loss"][-1]}
    result["finite"] = math.isfinite(result["final_loss"])
    # the timer must see the queued work: on CUDA its mean is close to the wall clock's, not a fraction of it
    result["timer_ok"] = result["timer_over_wall"] is None or result["timer_over_wall"] > 0.5
    result["status"] = "ok" if result["finite"] and not syncs["ours"] and result["timer_ok"] else "failed"
    return result


# ------------------------------------------------------------------------------------------------


def first_line(exc: BaseException, limit: int = 300) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:limit]


_REAL_STDOUT = sys.stdout


def log(message: str) -> None:
    print(f"sp-gpu-check: {message}", file=_REAL_STDOUT, flush=True)


def clean_json(obj: Any) -> Any:
    """Strict JSON: non-finite numbers become null, paths and other objects strings."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {str(k): clean_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean_json(v) for v in obj]
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


class Report:
    """The JSON report, rewritten after each part (and by the deadline's watchdog)."""

    def __init__(self, path: Path, data: dict) -> None:
        self.path, self.data = path, data
        self.lock = threading.Lock()

    def write(self) -> None:
        with self.lock:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps(clean_json(self.data), indent=2, allow_nan=False) + "\n")
            os.replace(tmp, self.path)


def summary_lines(report: dict) -> List[str]:
    lines = []
    parts = report.get("parts", {})
    grid = parts.get("grid")
    if grid and "agreement" in grid:
        a = grid["agreement"]
        lines.append(f"grid: {grid['status']}: against {grid['against']}: points over tolerance: output "
                     f"{a['output']['fraction_over_tolerance']:.2%}, input gradient {a['input_gradient']['fraction_over_tolerance']:.2%}; "
                     f"table gradient rel. L2 {a['table_gradient']['relative_l2']:.2e}; autocast "
                     f"{'ok' if grid['autocast']['ok'] else 'FAILED'} (SP moved {grid['autocast']['sp_moved_fraction']:.2%})")
        speed = grid.get("seconds_per_step", {})
        if "fit_torch_over_tcnn" in speed:
            lines.append(f"grid: torch / tcnn step time: fit {speed['fit_torch_over_tcnn']:.2f}x, eikonal "
                         f"{speed.get('eikonal_torch_over_tcnn', float('nan')):.2f}x")
    runs = parts.get("runs", {})
    for name, r in runs.get("runs", {}).items():
        if "seconds_per_step" in r:
            mem = r.get("memory", {}).get("allocator_peak_mib")
            lines.append(f"runs: {name}: {r['seconds_per_step'] * 1000:.1f} ms/step, grid {'/'.join(r['hash_grid'])}, syncs/step "
                         f"ours {r['syncs']['ours_per_step']:g} host {r['syncs']['host_per_step']:g}"
                         + (f", peak {mem:.0f} MiB" if mem is not None else ""))
        else:
            lines.append(f"runs: {name}: {r.get('status')}: {r.get('error')}")
    for key, v in runs.get("sp_overhead", {}).items():
        lines.append(f"runs: SP overhead on {key}: {v['ratio'] - 1:+.1%} per step" + ("" if v["comparable"] else " (different hash grids)"))
    for name, part in parts.items():
        for skip in ([part["reason"]] if "reason" in part else []) + part.get("skipped", []):
            lines.append(f"{name}: skipped {skip}")
        if part.get("status") == "failed":
            lines.append(f"{name}: FAILED" + (f": {part['error']}" if "error" in part else "")
                         + (f": {'; '.join(part['problems'])}" if part.get("problems") else ""))
    return lines


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="sp-gpu-check", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("gpu-check"), help="folder for the report and the runs (default: ./gpu-check)")
    ap.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu (the CPU paths only; default: cuda)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a CPU, or a smoke test)")
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS), help="what to run (default: all)")
    ap.add_argument("--require-tcnn", action="store_true", help="a missing tinycudann is a failure, not a skip")
    ap.add_argument("--deadline", type=float, default=DEADLINE_S, help=f"seconds for everything, start-up included (default: {DEADLINE_S:.0f})")
    ap.add_argument("--tolerance", type=float, default=1e-2, help="relative error per point, tcnn vs torch (default: 1e-2)")
    ap.add_argument("--max-bad-fraction", type=float, default=1e-2, help="points allowed over the tolerance (default: 0.01)")
    ap.add_argument("--table-tolerance", type=float, default=5e-2, help="relative L2 of the table gradients (default: 0.05)")
    args = ap.parse_args(argv)
    for name in ("deadline", "tolerance", "max_bad_fraction", "table_tolerance"):
        if not getattr(args, name) > 0:
            ap.error(f"--{name.replace('_', '-')} must be positive")
    if args.device != "cpu" and not args.device.startswith("cuda"):
        ap.error(f"--device {args.device}: use cuda, cuda:N or cpu")
    return args


def main(argv: Optional[Sequence[str]] = None, own_process: bool = False) -> int:
    """The check; ``own_process`` (the console command): the deadline counts from the process start
    and, once reached, ends the process. Called from Python (a test, another tool), the deadline
    counts from the call and a reached deadline only records itself: the caller's process lives on."""
    args = parse_args(argv)
    deadline = Deadline(args.deadline, since_process_start=own_process)
    import torch

    device = torch.device(args.device)
    if device.type == "cuda":
        problem = cuda_problem(args.device)
        if problem is not None:
            log(f"error: {problem}")
            return 1
        if device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        torch.cuda.set_device(device)
    os.environ.setdefault("PYTHONWARNINGS", "ignore::DeprecationWarning")
    sizes = Sizes(args.quick)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    report = Report(out / "gpu_check.json", {"command": ["sp-gpu-check", *(argv if argv is not None else sys.argv[1:])],
                                             "machine": machine_report(device), "quick": args.quick,
                                             "deadline_s": args.deadline, "parts": {}})
    parts = report.data["parts"]
    if device.type != "cuda":
        report.data["skipped"] = [f"--device {device}: no GPU part runs (tcnn, CUDA timings and memory, CUDA sync debug mode, "
                                  "fp16 autocast); what runs is the CPU path of each part"]
        log(report.data["skipped"][0])
    current = {"part": None}

    def on_deadline() -> None:
        part = current["part"]
        if part is not None:
            parts[part] = {"status": "failed", "error": f"cut by the deadline (--deadline {args.deadline:.0f} s) while running"}
        report.data["deadline_reached"] = True
        report.data["seconds"] = deadline.elapsed()
        report.write()
        log(f"error: the deadline of {args.deadline:.0f} s was reached" + (f" during {part}" if part else "")
            + f"; report -> {report.path}")
        if own_process:
            os._exit(1)

    watchdog = threading.Timer(max(deadline.remaining(), 0.0), on_deadline)
    watchdog.daemon = True
    watchdog.start()
    artifacts: dict = {}
    checks = {
        "grid": lambda: check_grid(device, sizes, args, deadline),
        "runs": lambda: check_runs(device, sizes, out, deadline, artifacts),
        "checkpoint": lambda: check_checkpoint(device, sizes, out, deadline, artifacts),
        "fit": lambda: check_fit(device, sizes, deadline),
    }
    needs = {"grid": 20, "runs": 60, "checkpoint": 20, "fit": 15}
    log_path = out / "log.txt"
    with open(log_path, "w") as host_output:
        for part in PARTS:
            if part not in args.parts:
                continue
            late = deadline.too_late(needs[part])
            if late:
                parts[part] = {"status": "failed", "reason": late}
                continue
            log(f"{part} ...")
            current["part"] = part
            start = time.perf_counter()
            try:
                with contextlib.redirect_stdout(host_output), contextlib.redirect_stderr(host_output):
                    parts[part] = checks[part]()
            except Exception as exc:  # a broken part is the finding: record it, run the others
                parts[part] = {"status": "failed", "error": f"{type(exc).__name__}: {first_line(exc)}"}
            current["part"] = None
            parts[part]["seconds"] = time.perf_counter() - start
            report.data["seconds"] = deadline.elapsed()
            report.write()
    watchdog.cancel()
    report.data["seconds"] = deadline.elapsed()
    report.write()
    for line in summary_lines(report.data):
        log(line)
    failed = [p for p, r in parts.items() if r.get("status") == "failed"]
    log(f"{'FAILED: ' + ', '.join(failed) if failed else 'ok'}; report -> {report.path} ({report.data['seconds'] / 60:.1f} min; "
        f"the hosts' output in {log_path})")
    return 1 if failed else 0


def entrypoint() -> None:
    sys.exit(main(own_process=True))


if __name__ == "__main__":
    entrypoint()
