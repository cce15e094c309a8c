"""How many torch threads a CPU job should use on a machine it may share."""

from __future__ import annotations

import os
import time


def usable_cores() -> int:
    """Cores this process may run on (the affinity mask, which containers and ``taskset`` narrow)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def free_cores(window: float = 0.3) -> int:
    """Cores that other processes leave idle, measured over ``window`` seconds (at least 1).

    Why: a torch op waits for its slowest thread, so a thread on a core another process keeps busy
    makes every op wait for a time slice. On our 2-core EPYC VM, with a 1-thread job beside it,
    the demo's step took 0.23 s with 2 threads and 0.11 s with 1. This process's own CPU time is
    left out: OpenMP workers spin for a while after the last parallel op.
    """
    import psutil

    cores = usable_cores()
    me = psutil.Process()
    me.cpu_percent(None), psutil.cpu_percent(None)  # start both counters
    time.sleep(window)
    total = psutil.cpu_percent(None) / 100.0 * (psutil.cpu_count() or cores)
    others = max(0.0, total - me.cpu_percent(None) / 100.0)
    return max(1, min(cores, round(cores - others)))


def pick_threads(requested: int | None, log=print, prog: str = "sp-plugins") -> int:
    """Set torch's intra-op threads: ``requested`` when given, else torch's default capped at the free cores."""
    import torch

    if requested is not None:
        if requested < 1:
            raise ValueError(f"--threads must be at least 1, got {requested}")
        torch.set_num_threads(requested)
        return requested
    default = torch.get_num_threads()  # torch's own choice: one per physical core
    cores, free = usable_cores(), free_cores()
    threads = min(default, free)
    if threads < default:
        log(f"[{prog}] {cores - free} of {cores} cores are busy with other processes: "
            f"using {threads} torch thread{'s' * (threads > 1)} (--threads N overrides)")
    torch.set_num_threads(threads)
    return threads
