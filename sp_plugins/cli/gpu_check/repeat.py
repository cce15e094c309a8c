"""Part ``repeat``: the same short training twice on the device, from the same seed, compared
bitwise, so the first run on a new machine says whether its runs repeat.

The run is ``sp-fit pointcloud``'s trainer (hash grid, SP on) under our deterministic-kernel scope
(``patches/torch_deterministic.py``: ``SP_DETERMINISTIC``; on a GPU its default leaves torch's
kernels as they are). On a CPU the two runs must match. On a GPU a mismatch is reported, not
failed: tiny-cuda-nn accumulates its hash-table gradients with atomics, whose order follows thread
scheduling, and torch's CUDA kernels repeat only with ``SP_DETERMINISTIC=1``.
"""

from __future__ import annotations

from importlib.resources import files

import torch

from sp_plugins.cli.gpu_check.budget import Deadline, Sizes
from sp_plugins.core import SPConfig
from sp_plugins.geometry import load_oriented_points
from sp_plugins.patches import registry
from sp_plugins.tasks import PointCloudSDFConfig
from sp_plugins.tasks.fields import EncodingConfig

TCNN_NOTE = ("tiny-cuda-nn accumulates hash-table gradients with atomics (their order follows thread scheduling): "
             "its runs differ in the last bits, and grow apart over training")


def train_once(device, sizes: Sizes, data) -> dict:
    """The parameters after ``sizes.fit_steps`` steps of a seeded point-cloud fit (on the CPU, by name)."""
    sp = SPConfig(alpha0=0.03, schedule="step", end=1.0)
    config = PointCloudSDFConfig(steps=sizes.fit_steps, seed=0, sp=sp)
    if sizes.quick:
        config = PointCloudSDFConfig(steps=sizes.fit_steps, seed=0, surface_batch=256, space_batch=256, hidden=(16,), sp=sp,
                                     encoding=EncodingConfig(levels=4, log2_table_size=12, base_resolution=8, max_resolution=64))
    trainer = config.setup(data, device=device)
    while not trainer.done:
        trainer.step()
    params = {name: p.detach().to("cpu", copy=True) for name, p in trainer.field.named_parameters()}
    return params, str(getattr(trainer.field.encoding, "backend", "none"))


def check_repeat(device, sizes: Sizes, deadline: Deadline) -> dict:
    data = load_oriented_points(str(files("sp_plugins.data") / "assets" / "spot.ply"), 50_000, 0)
    with registry.scope("torch_deterministic") as deterministic:
        (first, backend), (second, _) = train_once(device, sizes, data), train_once(device, sizes, data)
    differ = {name: float((first[name] - second[name]).abs().max()) for name in first if not torch.equal(first[name], second[name])}
    result = {"steps": sizes.fit_steps, "tensors": len(first), "differing": differ, "repeats": not differ,
              "deterministic_kernels": bool(deterministic), "hash_grid": backend}
    if device.type == "cuda":
        if differ:
            result["why"] = TCNN_NOTE if backend == "tcnn" else "torch's CUDA kernels: rerun with SP_DETERMINISTIC=1"
        result["status"] = "ok"  # a finding on a GPU, not a failure
    else:
        result["status"] = "ok" if not differ else "failed"
    return result

