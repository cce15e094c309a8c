"""The report: ``gpu_check.json`` (strict JSON, rewritten after each part), the progress lines and
the summary the command prints."""

from __future__ import annotations

import json
import math
import os
import sys
import threading
from pathlib import Path
from typing import Any, List

from sp_plugins.adapter.errors import first_line

def failure(exc: BaseException) -> str:
    """A part's or run's error as the report records it: the exception's type and first line."""
    line = first_line(exc, limit=300)
    return line if line.startswith(type(exc).__name__) else f"{type(exc).__name__}: {line}"


_REAL_STDOUT = sys.stdout


def log(message: str) -> None:
    """A progress line on the real stdout (the parts run with the hosts' output sent to the log)."""
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
    """What the command prints at the end: per part its findings, what it skipped and why."""
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
    repeat = parts.get("repeat", {})
    if "repeats" in repeat:
        lines.append(f"repeat: the same {repeat['steps']}-step fit twice ({repeat['hash_grid']} hash grid, deterministic kernels "
                     f"{'on' if repeat['deterministic_kernels'] else 'off'}): "
                     + ("bit-identical" if repeat["repeats"] else f"{len(repeat['differing'])} of {repeat['tensors']} tensors differ"
                        + (f" ({repeat['why']})" if "why" in repeat else "")))
    for name, part in parts.items():
        for skip in ([part["reason"]] if "reason" in part else []) + part.get("skipped", []):
            lines.append(f"{name}: skipped {skip}")
        if part.get("status") == "failed":
            lines.append(f"{name}: FAILED" + (f": {part['error']}" if "error" in part else "")
                         + (f": {'; '.join(part['problems'])}" if part.get("problems") else ""))
    return lines
