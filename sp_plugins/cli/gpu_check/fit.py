"""Part ``fit``: ``sp-fit pointcloud``'s trainer on the device: seconds per step from its timer
against the wall clock (the timer must see the queued work), no sync of ours per step."""

from __future__ import annotations

import math
import statistics
import time
from importlib.resources import files

from sp_plugins.cli.gpu_check.budget import Deadline, Sizes
from sp_plugins.cli.gpu_check.measure import count_syncs, synchronize
from sp_plugins.core import SPConfig
from sp_plugins.geometry import load_oriented_points
from sp_plugins.tasks import PointCloudSDFConfig
from sp_plugins.tasks.fields import EncodingConfig


def check_fit(device, sizes: Sizes, deadline: Deadline) -> dict:
    """Part ``fit``: ``sp-fit pointcloud``'s trainer on the device, its timer against the wall clock."""
    data = load_oriented_points(str(files("sp_plugins.data") / "assets" / "spot.ply"), 50_000, 0)
    sp = SPConfig(alpha0=0.03, schedule="step", end=1.0)  # SP on in every step, the counted ones too
    config = PointCloudSDFConfig(steps=sizes.fit_steps + 3, sp=sp)
    if sizes.quick:
        config = PointCloudSDFConfig(steps=sizes.fit_steps + 3, surface_batch=256, space_batch=256, hidden=(16,), sp=sp,
                                     encoding=EncodingConfig(levels=4, log2_table_size=12, base_resolution=8, max_resolution=64))
    trainer = config.setup(data, device=device)
    trainer.step()  # warm-up
    synchronize(device)
    start = time.perf_counter()
    for _ in range(sizes.fit_steps - 1):
        trainer.step()
    synchronize(device)
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
