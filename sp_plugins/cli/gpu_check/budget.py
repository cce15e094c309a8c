"""How long and how big: the deadline every part answers to, and the sizes of each part
(real on a GPU, tiny with ``--quick``)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Optional

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
