"""Shared plumbing for benchmarks: output folder, process set-up, machine info, seeding, paired timing."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import torch

OUT_DIR = Path(os.environ.get("SP_BENCH_OUT", Path(__file__).resolve().parents[1] / "out"))


def start(threads: int = 1, quiet: tuple = ("nerfstudio", "PIL")) -> None:
    """A bench process: ``threads`` torch / OpenMP threads (1 on a shared machine), INFO logging with
    times, and the ``quiet`` libraries' loggers at WARNING."""
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    torch.set_num_threads(threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    for name in quiet:
        logging.getLogger(name).setLevel(logging.WARNING)


def machine_info() -> dict:
    """What the numbers came from: the load matters on a shared 2-core machine."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "loadavg_1_5_15": [round(v, 2) for v in load],
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def seed_everything(seed: int) -> None:
    """Seed torch, numpy and Python's `random`: the hosts' data loaders draw from all three (nerfstudio's
    CacheDataloader orders its cached images with ``random.sample``), so a pair of runs sees the same
    rays only when every one of them is seeded."""
    import random

    import numpy as np

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def paired_timing(steps: Dict[str, Callable[[], None]], repeats: int, warmup: int = 3) -> Dict[str, List[float]]:
    """Run the given step functions in alternation (A B A B ...), so that load spikes on a
    shared machine hit all of them alike. Returns seconds per call for each name."""
    for _ in range(warmup):
        for fn in steps.values():
            fn()
    times: Dict[str, List[float]] = {k: [] for k in steps}
    names = list(steps)
    for i in range(repeats):
        order = names if i % 2 == 0 else names[::-1]
        for name in order:
            t0 = time.perf_counter()
            steps[name]()
            times[name].append(time.perf_counter() - t0)
    return times


def ratio_summary(times: Dict[str, List[float]], baseline: str) -> dict:
    """Median seconds per step and the median of per-pair ratios against ``baseline``."""
    out = {}
    base = times[baseline]
    for name, ts in times.items():
        pair_ratios = [t / b for t, b in zip(ts, base)]
        out[name] = {
            "median_s": statistics.median(ts),
            "ratio_vs_" + baseline: statistics.median(pair_ratios) if name != baseline else 1.0,
            "ratio_of_medians": statistics.median(ts) / statistics.median(base),
        }
    return out


def safe_name(run: str) -> str:
    """A run's name as a file or folder name (``sp-relu-field[8vox,end0.3]`` -> ``sp-relu-field_8vox_end0.3``)."""
    return run.replace("[", "_").replace("]", "").replace(",", "_")


def done_or_run(path: Path, overwrite: bool, run: Callable[[], dict]) -> Tuple[dict, bool]:
    """A resumable result: the one at ``path`` if it is there (logged as done already) unless ``overwrite``,
    else ``run()``'s, written to ``path``. Returns ``(result, whether it was computed now)``."""
    if path.is_file() and not overwrite:
        logging.info("done already: %s", path.name)
        return json.loads(path.read_text()), False
    result = run()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1))
    return result, True


@dataclasses.dataclass
class GridFieldSize:
    """The size of a NeuS-family SDF field (hash grid and MLPs) at a CPU budget, shared by the SDF studies."""

    hidden_dim: int = 64
    """width of the SDF and colour MLPs"""
    geo_feat_dim: int = 31
    """geometry features handed from the SDF MLP to the colour MLP"""
    num_levels: int = 16
    """hash levels"""
    max_res: int = 256
    """the hash grid's finest resolution"""
    log2_hashmap_size: int = 16
    """log2 of the hash table's rows per level"""

    def field_settings(self) -> dict:
        """The field config's settings (``shrink(config, field=...)``); the colour MLP as wide as the SDF's."""
        return dict(hidden_dim=self.hidden_dim, hidden_dim_color=self.hidden_dim, geo_feat_dim=self.geo_feat_dim,
                    num_levels=self.num_levels, max_res=self.max_res, log2_hashmap_size=self.log2_hashmap_size)


@dataclasses.dataclass
class NeuSBudget(GridFieldSize):
    """What a NeuS-family pair's CPU-sized setting states besides its field (``sdf_methods``,
    ``sdfstudio_neus_facto``): each study extends it with its sampler and overrides the defaults."""

    steps: int = 400
    """training steps of every run"""
    rays: int = 256
    """rays per training batch"""
    lr: float = 5e-3
    """Adam learning rate of the fields"""
    warm_up_end: int = 100
    """steps of the learning rate's linear warm-up"""
    views: int = 24
    """training views of the rendered scene"""
    resolution: int = 64
    """side in pixels of the renders"""
    mesh_resolution: int = 128
    """marching-cubes grid points per axis of the final meshes"""


def write_json(name: str, payload: dict) -> Path:
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    path = OUT_DIR / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2))
    return path
