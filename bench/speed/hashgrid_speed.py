"""Our torch HashGrid against nerfstudio's torch HashEncoding: a whole training step, side by side.

Setting (the paper's hash grid): 16 levels, 2^19 rows per level, resolution 16 to 2048,
2 features per level, 2^16 points per step, a 32-64-64-1 MLP, Adam (lr 1e-2) over encoding + MLP,
the same optimizer for both: torch's default Adam (``foreach``) and, as a second setting, the
fused CPU Adam (``fused=True``). Two workloads:

- ``fit``: regress a target from fixed points (no input gradient): forward, backward, Adam step;
- ``eikonal``: the same plus an eikonal term, which differentiates the input gradient again
  (double backward through the encoding), as the SDF tasks do.

Steps of the two implementations alternate in one process (A B B A ...), so load on the shared
machine hits both alike; the ratio of the medians is the result. Peak memory is measured per
variant in a fresh subprocess: peak RSS during the steps minus RSS just before building the
model (the model's table, optimizer state and per-step temporaries).

Usage: ``python -m bench.speed.hashgrid_speed [--points 65536] [--repeats 12] [--threads 2]``
Writes ``bench/out/hashgrid_speed.json`` and ``bench/out/hashgrid_speed.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from typing import Callable, Dict, Tuple

import torch
from torch import nn

from bench.harness.common import OUT_DIR, machine_info, paired_timing, ratio_summary, write_json

SETTING = dict(num_levels=16, log2_hashmap_size=19, base_resolution=16, max_resolution=2048, features_per_level=2)
VARIANTS = ("nerfstudio", "ours")
WORKLOADS = ("fit", "eikonal")
OPTIMIZERS = {"adam": {}, "adam-fused": {"fused": True}}


def build_encoding(variant: str) -> nn.Module:
    if variant == "nerfstudio":
        from nerfstudio.field_components.encodings import HashEncoding

        s = SETTING
        return HashEncoding(s["num_levels"], s["base_resolution"], s["max_resolution"], s["log2_hashmap_size"], s["features_per_level"], implementation="torch")
    from sp_plugins.encodings import HashGrid

    return HashGrid(**SETTING, backend="torch")


def make_step(variant: str, workload: str, points: int, optimizer: str = "adam", seed: int = 0) -> Tuple[Callable[[], float], nn.Module]:
    torch.manual_seed(seed)
    enc = build_encoding(variant)
    width = SETTING["num_levels"] * SETTING["features_per_level"]
    mlp = nn.Sequential(nn.Linear(width, 64), nn.ReLU(), nn.Linear(64, 64), nn.Softplus(beta=100), nn.Linear(64, 1))
    opt = torch.optim.Adam(list(enc.parameters()) + list(mlp.parameters()), lr=1e-2, **OPTIMIZERS[optimizer])
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(points, 3, generator=gen)
    target = (x - 0.5).norm(dim=-1, keepdim=True) - 0.3

    def step() -> float:
        if workload == "eikonal":
            xs = x.clone().requires_grad_(True)
            f = mlp(enc(xs))
            (g,) = torch.autograd.grad(f.sum(), xs, create_graph=True)
            loss = (f - target).square().mean() + 0.1 * (g.norm(dim=-1) - 1).square().mean()
        else:
            loss = (mlp(enc(x)) - target).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return float(loss.detach())

    return step, enc


def _status_kb(field: str) -> int:
    """``VmRSS`` (now) or ``VmHWM`` (peak) of this process, from /proc (Linux). ``ru_maxrss`` is no
    good here: it survives exec, so a child started by a big parent inherits the parent's peak."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not found in /proc/self/status (peak memory needs Linux)")


def measure_memory(variant: str, workload: str, optimizer: str, points: int, steps: int) -> dict:
    """Run in a fresh process: peak RSS of building + ``steps`` steps over the RSS before."""
    before = _status_kb("VmRSS")
    step, _ = make_step(variant, workload, points, optimizer)
    for _ in range(steps):
        step()
    peak = _status_kb("VmHWM")
    return {"peak_rss_mb": peak / 1024, "peak_over_start_mb": (peak - before) / 1024}


def memory_in_subprocess(variant: str, workload: str, optimizer: str, points: int, steps: int, threads: int) -> dict:
    cmd = [sys.executable, "-m", "bench.speed.hashgrid_speed", "--memory-probe", variant, "--workload", workload,
           "--optimizer", optimizer, "--points", str(points), "--memory-steps", str(steps), "--threads", str(threads)]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=root, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def sparse_update_estimate(points: int) -> dict:
    """Would a row-sparse optimizer pay off? Share of table rows one step touches, the cost of just
    finding them (``unique``, a lower bound on any sparse update's overhead) and the cost of a dense
    Adam step over the whole table (default and fused)."""
    import time

    from sp_plugins.encodings import HashGrid
    from sp_plugins.encodings.hashgrid_torch import corner_indices

    grid = HashGrid(**SETTING, backend="torch")
    x = torch.rand(points, 3, generator=torch.Generator().manual_seed(0))
    scales = torch.tensor([lv.scale for lv in grid.levels])
    cell = torch.floor(x.t()[None] * scales[:, None, None] + 0.5).long()
    rows = corner_indices(cell, grid.levels, 2 ** SETTING["log2_hashmap_size"]).long()
    rows += torch.tensor([lv.offset for lv in grid.levels])[:, None, None]
    t0 = time.perf_counter()
    touched = int(torch.unique(rows).numel())
    unique_s = time.perf_counter() - t0
    adam_s = {}
    for name, kwargs in OPTIMIZERS.items():
        opt = torch.optim.Adam([grid.table], lr=1e-2, **kwargs)
        grid.table.grad = torch.randn_like(grid.table)
        opt.step()
        t0 = time.perf_counter()
        opt.step()
        adam_s[name] = time.perf_counter() - t0
    return {"rows": grid.n_table_rows, "rows_touched": touched, "fraction": touched / grid.n_table_rows,
            "unique_rows_s": unique_s, "dense_adam_step_s": adam_s}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, default=2**16)
    parser.add_argument("--repeats", type=int, default=12, help="timed steps per variant and workload")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--workload", choices=WORKLOADS + ("both",), default="both")
    parser.add_argument("--optimizer", choices=tuple(OPTIMIZERS) + ("both",), default="both")
    parser.add_argument("--memory-steps", type=int, default=3)
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--memory-probe", choices=VARIANTS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    if args.memory_probe:
        print(json.dumps(measure_memory(args.memory_probe, args.workload, args.optimizer, args.points, args.memory_steps)))
        return

    workloads = WORKLOADS if args.workload == "both" else (args.workload,)
    optimizers = tuple(OPTIMIZERS) if args.optimizer == "both" else (args.optimizer,)
    result: Dict[str, object] = {"setting": dict(SETTING, points=args.points, optimizer="torch.optim.Adam(lr=1e-2)", mlp="32-64-64-1"),
                                 "command": " ".join(["python -m bench.speed.hashgrid_speed"] + (argv if argv is not None else sys.argv[1:])),
                                 "machine_before": machine_info(), "runs": {}}
    for workload in workloads:
        for optimizer in optimizers:
            key = f"{workload}/{optimizer}"
            steps = {v: make_step(v, workload, args.points, optimizer)[0] for v in VARIANTS}
            times = paired_timing(steps, repeats=args.repeats, warmup=args.warmup)
            summary = ratio_summary(times, baseline="nerfstudio")
            entry = {"workload": workload, "optimizer": optimizer, "seconds": times, "summary": summary,
                     "speedup_ours_vs_nerfstudio": summary["nerfstudio"]["median_s"] / summary["ours"]["median_s"]}
            del steps
            if not args.skip_memory:
                entry["memory"] = {v: memory_in_subprocess(v, workload, optimizer, args.points, args.memory_steps, args.threads) for v in VARIANTS}
            result["runs"][key] = entry
            print(f"[{key}] nerfstudio {summary['nerfstudio']['median_s']:.3f} s/step, ours {summary['ours']['median_s']:.3f} s/step, "
                  f"speed-up {entry['speedup_ours_vs_nerfstudio']:.2f}x", flush=True)
    result["sparse_update_estimate"] = sparse_update_estimate(args.points)
    result["machine_after"] = machine_info()
    path = write_json("hashgrid_speed", result)
    md = to_markdown(result)
    (OUT_DIR / "hashgrid_speed.md").write_text(md)
    print(md)
    print(f"wrote {path}")


def to_markdown(result: dict) -> str:
    lines = ["| workload | optimizer | nerfstudio s/step | ours s/step | speed-up | nerfstudio peak MB | ours peak MB |",
             "|---|---|---|---|---|---|---|"]
    for e in result["runs"].values():
        s = e["summary"]
        mem = e.get("memory", {})
        mn = f"{mem['nerfstudio']['peak_over_start_mb']:.0f}" if mem else "-"
        mo = f"{mem['ours']['peak_over_start_mb']:.0f}" if mem else "-"
        lines.append(f"| {e['workload']} | {e['optimizer']} | {s['nerfstudio']['median_s']:.3f} | {s['ours']['median_s']:.3f} | "
                     f"{e['speedup_ours_vs_nerfstudio']:.2f}x | {mn} | {mo} |")
    t = result["sparse_update_estimate"]
    lines.append("")
    lines.append(f"Rows touched per step: {t['rows_touched']} of {t['rows']} ({100 * t['fraction']:.0f}%); finding them "
                 f"(unique) {t['unique_rows_s']:.3f} s; dense Adam step on the table {t['dense_adam_step_s']['adam']:.3f} s, "
                 f"fused {t['dense_adam_step_s']['adam-fused']:.3f} s. "
                 f"Load before/after: {result['machine_before']['loadavg_1_5_15']} / {result['machine_after']['loadavg_1_5_15']}.")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
