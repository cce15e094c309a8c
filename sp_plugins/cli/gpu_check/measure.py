"""Timing, memory and host-device syncs of training steps, on CUDA as a GPU run sees them and on a
CPU along the same branches."""

from __future__ import annotations

import contextlib
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, List

import torch

from sp_plugins.core.boundary import dense_fold
from sp_plugins.sync_count import SyncCounter, site_of

OWN_FILES = [str(p) for p in Path(__file__).parent.glob("*.py")]
"""This check's own modules: the driver that calls the host's trainer, no site of a sync."""


def synchronize(device) -> None:
    """Wait for ``device``'s queued work (CUDA only)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_steps(step: Callable[[int], Any], first: int, count: int, device) -> List[float]:
    """Seconds of each of ``count`` steps: CUDA events on CUDA (queued work included, no sync
    between steps), the wall clock elsewhere."""
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


def count_syncs(step: Callable[[int], Any], first: int, count: int, device) -> dict:
    """Stalling ops per step over ``count`` steps, ours and the host's by site; on a CPU along the
    branches a GPU takes (the reflect boundary's dense fold, :func:`sp_plugins.core.boundary.dense_fold`:
    the CPU's sparse fold reads a count back on purpose, cheap there); on CUDA also what
    ``torch.cuda.set_sync_debug_mode`` reports (the syncs that really happened)."""
    records: list = []
    counter = SyncCounter(devices={"cuda"} if device.type == "cuda" else None, skip_files=OWN_FILES)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if device.type == "cuda":
            torch.cuda.set_sync_debug_mode("warn")
        try:
            with (dense_fold() if device.type != "cuda" else contextlib.nullcontext()), counter:
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
        if self.device.type == "cuda":
            synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.start = torch.cuda.memory_allocated(self.device)
            free, total = torch.cuda.mem_get_info(self.device)
            self.device_start = total - free
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            synchronize(self.device)
            free, total = torch.cuda.mem_get_info(self.device)
            self.result = {
                "allocator_peak_mib": torch.cuda.max_memory_allocated(self.device) / 2**20,
                "allocator_peak_over_start_mib": (torch.cuda.max_memory_allocated(self.device) - self.start) / 2**20,
                "reserved_peak_mib": torch.cuda.max_memory_reserved(self.device) / 2**20,
                "device_used_growth_mib": (total - free - self.device_start) / 2**20,  # tcnn's own allocations land here too
            }
