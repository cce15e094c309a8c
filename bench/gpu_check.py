"""The first thing to run on a machine with an NVIDIA GPU (under 10 minutes): do the GPU paths work?

    python bench/gpu_check.py                 # writes gpu-check/gpu_check.json
    python bench/gpu_check.py --out DIR --neus-steps 300 --fit-steps 300

It checks what no CPU test can see:

1. ``grid``: tiny-cuda-nn's hash grid against our torch backend on CUDA, from the same weights
   (our ``table`` loaded into a ``backend="tcnn"`` grid through the checkpoint mapping): outputs
   and input gradients agree (relative to their scale; tcnn keeps half-precision parameters on
   most GPUs, so about 1e-3 is expected, the tolerance is ``--tolerance``), and the time of a fit
   step and of an eikonal step (double backward) for each, with their peak memory. Skipped, with
   the reason in the report, when ``tinycudann`` does not import.
2. ``neus``: ``ns-train sp-neus-hashgrid`` for a few hundred steps on CUDA on a small scene made
   by ``sp-scene`` (a subprocess, as a user runs it): exit code, seconds per step, which hash-grid
   backend the checkpoint holds, and the peak GPU memory in use while it ran; then ``ns-eval`` of
   that GPU checkpoint with CUDA hidden (``CUDA_VISIBLE_DEVICES=""``), as on a machine without a
   GPU: the checkpoint must load into the torch backend and evaluate.
3. ``fit``: ``sp-fit pointcloud`` on the bundled Spot mesh with ``--device cuda``: exit code,
   seconds per step, Chamfer distance, peak GPU memory.

Without CUDA it prints one line saying why it skipped and exits 0. Each part is independent: a
failing part is recorded (with the tail of its output) and the others still run; the exit code
is 1 when any part failed. Send ``gpu_check.json`` along with a bug report.
"""

from __future__ import annotations

import argparse
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
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import torch

PARTS = ("grid", "neus", "fit")
GRID_SETTING = dict(num_levels=16, features_per_level=2, log2_hashmap_size=19, base_resolution=16, max_resolution=2048)
"""The paper's hash grid."""


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="gpu_check", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("gpu-check"), help="folder for the report and the runs (default: ./gpu-check)")
    ap.add_argument("--device", default="cuda", help="CUDA device to check (default: cuda)")
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS), help="what to run (default: all)")
    ap.add_argument("--grid-points", type=int, default=2**18, help="points per grid step (default: 2^18)")
    ap.add_argument("--grid-repeats", type=int, default=20, help="timed steps per grid backend (default: 20)")
    ap.add_argument("--tolerance", type=float, default=1e-2, help="relative agreement tcnn vs torch (default: 1e-2)")
    ap.add_argument("--neus-steps", type=int, default=300, help="ns-train sp-neus-hashgrid steps (default: 300)")
    ap.add_argument("--fit-steps", type=int, default=300, help="sp-fit pointcloud steps (default: 300)")
    ap.add_argument("--timeout", type=float, default=240.0, help="seconds allowed per subprocess (default: 240)")
    args = ap.parse_args(argv)
    for name in ("grid_points", "grid_repeats", "neus_steps", "fit_steps"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be at least 1")
    if not args.tolerance > 0:
        ap.error("--tolerance must be positive")
    return args


def cuda_skip_reason(device: str = "cuda") -> Optional[str]:
    """Why the check cannot run here (None when it can)."""
    if not torch.cuda.is_available():
        return "no CUDA device (torch.cuda.is_available() is False); run it on a machine with an NVIDIA GPU"
    try:
        dev = torch.device(device)
    except RuntimeError:
        return f"--device {device} is not a device"
    if dev.type != "cuda":
        return f"--device {device} is not a CUDA device"
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        return f"--device {device}: this machine has {torch.cuda.device_count()} CUDA device(s)"
    return None


# ------------------------------------------------------------------------------------------------
# part 1: the hash grid


def agreement(reference: torch.nn.Module, candidate: torch.nn.Module, x: torch.Tensor, tolerance: float = 1e-2) -> dict:
    """Outputs and input gradients of two encodings at ``x`` (on the same device), relative to the
    reference's scale. The input gradient is that of ``sum(out * w)`` for a fixed weight vector."""
    x = x.detach().requires_grad_(True)
    ref = reference(x)
    cand = candidate(x)
    if ref.shape != cand.shape:
        raise ValueError(f"output shapes differ: {tuple(ref.shape)} vs {tuple(cand.shape)}")
    w = torch.linspace(-1.0, 1.0, ref.shape[-1], device=x.device)
    (g_ref,) = torch.autograd.grad((ref.float() * w).sum(), x)
    (g_cand,) = torch.autograd.grad((cand.float() * w).sum(), x)

    def compare(a: torch.Tensor, b: torch.Tensor) -> Dict[str, float]:
        diff = float((a.float() - b.float()).abs().max())
        scale = float(a.float().abs().max())
        return {"max_abs_diff": diff, "scale": scale, "relative": diff / scale if scale > 0 else diff}

    out = {"output": compare(ref.detach(), cand.detach()), "input_gradient": compare(g_ref, g_cand), "tolerance": tolerance}
    out["ok"] = out["output"]["relative"] <= tolerance and out["input_gradient"]["relative"] <= tolerance
    return out


def _cuda_timing(fn: Callable[[], None], repeats: int, device) -> Dict[str, float]:
    fn()  # warm-up (kernels, allocator)
    torch.cuda.synchronize(device)
    torch.cuda.reset_peak_memory_stats(device)
    before = torch.cuda.memory_allocated(device)
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        torch.cuda.synchronize(device)
        times.append(start.elapsed_time(end) / 1000.0)
    return {"median_s": statistics.median(times), "peak_mib_over_start": (torch.cuda.max_memory_allocated(device) - before) / 2**20}


def grid_steps(grid: torch.nn.Module, points: int, device) -> Dict[str, Callable[[], None]]:
    """A fit step (forward, backward into the table) and an eikonal step (the input gradient's norm
    differentiated again), on fresh points each call, with a small MLP."""
    mlp = torch.nn.Sequential(torch.nn.Linear(grid.n_output_dims, 64), torch.nn.Softplus(beta=100), torch.nn.Linear(64, 1)).to(device)

    def fit() -> None:
        x = torch.rand(points, 3, device=device)
        loss = mlp(grid(x).float()).square().mean()
        loss.backward()

    def eikonal() -> None:
        x = torch.rand(points, 3, device=device, requires_grad=True)
        f = mlp(grid(x).float())
        (g,) = torch.autograd.grad(f.sum(), x, create_graph=True)
        ((g.norm(dim=-1) - 1).square().mean() + f.square().mean()).backward()

    return {"fit": fit, "eikonal": eikonal}


def check_grid(device: str, points: int, repeats: int, tolerance: float) -> dict:
    from sp_plugins.encodings import HashGrid, tcnn_usable

    if not tcnn_usable(device):
        return {"status": "skipped", "reason": "tinycudann does not import on this machine (pip install 'sp-plugins[tcnn]')"}
    if torch.device(device).index is not None:
        torch.cuda.set_device(torch.device(device))  # tcnn builds on the current device
    torch.manual_seed(0)
    reference = HashGrid(**GRID_SETTING, backend="torch", init_scale=1.0).to(device)
    candidate = HashGrid(**GRID_SETTING, backend="tcnn")
    candidate.load_state_dict(reference.state_dict())  # torch table -> tcnn params: the checkpoint mapping
    x = torch.rand(min(points, 2**16), 3, device=device)
    result = {"status": "ok", "setting": GRID_SETTING, "agreement": agreement(reference, candidate, x, tolerance)}
    back = HashGrid(**GRID_SETTING, backend="torch").to(device)
    back.load_state_dict(candidate.state_dict())  # and back: bit-identical
    result["round_trip_identical"] = bool(torch.equal(back.table, reference.table))
    speed: dict = {"torch": {}, "tcnn": {}}
    result["speed"] = speed
    failed = False
    for name, grid in (("torch", reference), ("tcnn", candidate)):
        for kind, step in grid_steps(grid, points, device).items():
            try:  # e.g. a tcnn build without double backward fails the eikonal step: keep the rest
                speed[name][kind] = _cuda_timing(step, repeats, device)
            except Exception as exc:
                speed[name][kind] = {"error": f"{type(exc).__name__}: {exc}"}
                failed = True
    for kind in ("fit", "eikonal"):
        if "median_s" in speed["torch"][kind] and "median_s" in speed["tcnn"][kind]:
            speed[f"{kind}_torch_over_tcnn"] = speed["torch"][kind]["median_s"] / speed["tcnn"][kind]["median_s"]
    if failed or not (result["agreement"]["ok"] and result["round_trip_identical"]):
        result["status"] = "failed"
    return result


# ------------------------------------------------------------------------------------------------
# parts 2 and 3: the commands a user runs


class GPUMemoryWatch:
    """Peak device memory in use (all processes, from ``cudaMemGetInfo``) while a command runs."""

    def __init__(self, device, interval: float = 0.2) -> None:
        self.device, self.interval = torch.device(device), interval
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _used(self) -> int:
        free, total = torch.cuda.mem_get_info(self.device)
        return total - free

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._used())
            time.sleep(self.interval)

    def __enter__(self) -> "GPUMemoryWatch":
        self.start = self._used()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def peak_mib_over_start(self) -> float:
        return max(self.peak - self.start, 0) / 2**20


def _tool(name: str) -> str:
    return shutil.which(name) or str(Path(sys.executable).parent / name)


def run_command(cmd: List[str], device, timeout: float, env: Optional[Dict[str, str]] = None) -> dict:
    """Run ``cmd``; exit code, seconds, peak GPU memory, and the tail of its output on failure."""
    start = time.perf_counter()
    with GPUMemoryWatch(device) as watch:
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
            code, output = proc.returncode, proc.stdout + proc.stderr
        except subprocess.TimeoutExpired as exc:
            code, output = None, f"timed out after {timeout:.0f} s\n{exc.stdout or ''}{exc.stderr or ''}"
    result = {"command": " ".join(cmd), "returncode": code, "seconds": time.perf_counter() - start,
              "peak_gpu_mib_over_start": watch.peak_mib_over_start}
    if code != 0:
        result["output_tail"] = output[-3000:] if isinstance(output, str) else str(output)[-3000:]
    return result


def neus_command(scene: Path, out: Path, steps: int, device: str) -> List[str]:
    return [
        _tool("ns-train"), "sp-neus-hashgrid", "--machine.device-type", "cuda", "--max-num-iterations", str(steps),
        "--steps-per-save", str(steps), "--vis", "tensorboard", "--timestamp", "gpu-check",
        "--logging.local-writer.enable", "False", "--pipeline.datamanager.train-num-rays-per-batch", "1024",
        "--output-dir", str(out), "blender-data", "--data", str(scene / "blender"),
    ]


def check_neus(out: Path, steps: int, device: str, timeout: float) -> dict:
    scene = out / "scene"
    made = run_command([_tool("sp-scene"), "sphere", str(scene), "--views", "24", "--val-views", "2", "--test-views", "2",
                         "--resolution", "64", "--overwrite", "--quiet"], device, timeout)
    if made["returncode"] != 0:
        return {"status": "failed", "stage": "sp-scene", **made}
    result = run_command(neus_command(scene, out / "neus", steps, device), device, timeout)
    result["steps"] = steps
    result["seconds_per_step"] = result["seconds"] / steps  # includes start-up: an upper bound
    ckpts = sorted((out / "neus").glob("**/nerfstudio_models/step-*.ckpt"))
    if ckpts:
        state = torch.load(ckpts[-1], map_location="cpu", weights_only=True)["pipeline"]  # our method: float learning rates
        result["checkpoint"] = str(ckpts[-1])
        result["grid_keys"] = sorted(k for k in state if k.endswith(("encoding.table", "encoding.tcnn_encoding.params")))
    configs = sorted((out / "neus").glob("**/config.yml"))
    if result["returncode"] == 0 and configs:
        # the GPU checkpoint on a CPU, as on a machine without a GPU: the real ns-eval, CUDA hidden
        cpu_env = dict(os.environ, CUDA_VISIBLE_DEVICES="", OMP_WAIT_POLICY="PASSIVE")
        metrics_path = out / "neus_eval_on_cpu.json"
        cmd = [_tool("ns-eval"), "--load-config", str(configs[-1]), "--output-path", str(metrics_path)]
        result["eval_on_cpu"] = run_command(cmd, device, 2 * timeout, env=cpu_env)  # CPU rendering is slower
        if metrics_path.is_file():
            result["eval_on_cpu"]["results"] = json.loads(metrics_path.read_text()).get("results")
    ok_eval = result.get("eval_on_cpu", {}).get("returncode") == 0
    result["status"] = "ok" if result["returncode"] == 0 and ckpts and ok_eval else "failed"
    return result


def check_fit(out: Path, steps: int, device: str, timeout: float) -> dict:
    from importlib.resources import files

    mesh = files("sp_plugins.data") / "assets" / "spot.ply"
    cmd = [_tool("sp-fit"), "pointcloud", str(mesh), "--device", device, "--steps", str(steps), "--out", str(out / "fit"),
           "--overwrite", "--quiet"]
    result = run_command(cmd, device, timeout)
    metrics_path = out / "fit" / "metrics.json"
    if result["returncode"] == 0 and metrics_path.is_file():
        m = json.loads(metrics_path.read_text())
        result.update(steps=m["steps"], seconds_per_step=m["seconds_per_step"], chamfer=m.get("chamfer"), device=m.get("device"))
        result["status"] = "ok" if str(m.get("device", "")).startswith("cuda") else "failed"
    else:
        result["status"] = "failed"
    return result


# ------------------------------------------------------------------------------------------------


def machine_report(device: Optional[str]) -> dict:
    info = {"python": platform.python_version(), "torch": torch.__version__, "cuda_runtime": torch.version.cuda,
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    if device is not None and torch.cuda.is_available():
        props = torch.cuda.get_device_properties(torch.device(device))
        info.update(gpu=props.name, gpu_memory_gib=round(props.total_memory / 2**30, 1), capability=f"{props.major}.{props.minor}")
    try:
        from importlib.metadata import version

        info["tinycudann"] = version("tinycudann")
    except Exception:  # not installed, or installed without metadata
        info["tinycudann"] = None
    return info


def write_report(path: Path, report: dict) -> Path:
    """The report as strict JSON (non-finite numbers become null)."""

    def clean(obj):
        if isinstance(obj, float) and not math.isfinite(obj):
            return None
        if isinstance(obj, dict):
            return {str(k): clean(v) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            return [clean(v) for v in obj]
        return obj

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(clean(report), indent=2, allow_nan=False) + "\n")
    return path


def summary_lines(report: dict) -> List[str]:
    lines = []
    grid = report.get("grid")
    if grid:
        if grid["status"] == "skipped":
            lines.append(f"grid: skipped ({grid['reason']})")
        elif "agreement" in grid:
            a = grid["agreement"]
            speed = grid.get("speed", {})
            ratios = ", ".join(f"{k} {speed[f'{k}_torch_over_tcnn']:.2f}x" if f"{k}_torch_over_tcnn" in speed else f"{k} n/a"
                               for k in ("fit", "eikonal"))
            lines.append(f"grid: {grid['status']}: tcnn vs torch output {a['output']['relative']:.2e}, input gradient "
                         f"{a['input_gradient']['relative']:.2e} (tolerance {a['tolerance']:.0e}); torch/tcnn time: {ratios}")
        else:
            lines.append(f"grid: {grid['status']}: {grid.get('error', '')}")
    for part in ("neus", "fit"):
        r = report.get(part)
        if r:
            extra = f", {r['seconds_per_step']:.3f} s/step, peak GPU +{r['peak_gpu_mib_over_start']:.0f} MiB" if "seconds_per_step" in r else ""
            lines.append(f"{part}: {r['status']}{extra}")
    return lines


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    reason = cuda_skip_reason(args.device)
    if reason is not None:
        print(f"gpu_check: skipped: {reason}")
        return 0
    os.environ.setdefault("PYTHONWARNINGS", "ignore::DeprecationWarning")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"machine": machine_report(args.device), "parts": args.parts}
    start = time.perf_counter()
    checks = {
        "grid": lambda: check_grid(args.device, args.grid_points, args.grid_repeats, args.tolerance),
        "neus": lambda: check_neus(out, args.neus_steps, args.device, args.timeout),
        "fit": lambda: check_fit(out, args.fit_steps, args.device, args.timeout),
    }
    for part in PARTS:
        if part not in args.parts:
            continue
        print(f"gpu_check: {part} ...", flush=True)
        try:
            report[part] = checks[part]()
        except Exception as exc:  # a broken part is the finding: record it, run the others
            report[part] = {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
        report["seconds"] = time.perf_counter() - start
        write_report(out / "gpu_check.json", report)
    for line in summary_lines(report):
        print(f"gpu_check: {line}")
    print(f"gpu_check: report -> {out / 'gpu_check.json'} ({report['seconds'] / 60:.1f} min)")
    return 1 if any(report[p]["status"] == "failed" for p in args.parts) else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file from a checkout
    sys.exit(main())
