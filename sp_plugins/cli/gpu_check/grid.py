"""Part ``grid``: tiny-cuda-nn's hash grid against our torch backend from the same weights (outputs
and input gradients judged by the fraction of points over a relative tolerance, table gradients
as whole vectors, the weights' round trip), our grid and SP under ``torch.autocast``, and on CUDA
fit and eikonal step times of both."""

from __future__ import annotations

import math
import statistics
from typing import Callable, Dict

import torch

from sp_plugins.cli.gpu_check.budget import Deadline, Sizes
from sp_plugins.cli.gpu_check.machine import tcnn_reason
from sp_plugins.cli.gpu_check.measure import time_steps
from sp_plugins.core import perturb
from sp_plugins.encodings import HashGrid
from sp_plugins.encodings.tcnn_layout import TcnnLayoutEncoding


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
    a, b = reference.detach().float().reshape(-1), candidate.detach().float().reshape(-1)
    rel = float((a - b).norm() / a.norm().clamp_min(1e-30))
    cos = float(torch.nn.functional.cosine_similarity(a, b, dim=0))
    return {"relative_l2": rel, "cosine": cos, "tolerance": tolerance, "ok": rel <= tolerance and math.isfinite(rel)}


def agreement(reference, candidate, x, tolerance: float = 1e-2, max_bad_fraction: float = 1e-2, table_tolerance: float = 5e-2) -> dict:
    """Outputs, input gradients and table gradients of two grids holding the same weights, at ``x``."""
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


def check_grid(device, sizes: Sizes, deadline: Deadline, tolerance: float = 1e-2, max_bad_fraction: float = 1e-2,
               table_tolerance: float = 5e-2, require_tcnn: bool = False) -> dict:
    """tiny-cuda-nn against our torch grid from the same weights (or, without it, against the
    :mod:`~sp_plugins.encodings.tcnn_layout` stand-in), autocast, and on CUDA both grids' step times;
    ``require_tcnn``: a missing tinycudann fails the part instead of being skipped."""
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
    result["agreement"] = agreement(reference, candidate, x, tolerance, max_bad_fraction, table_tolerance)
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
    if reason is not None and require_tcnn:
        result["error"] = f"--require-tcnn: {reason}"
        ok = False
    result["status"] = "ok" if ok else "failed"
    return result
