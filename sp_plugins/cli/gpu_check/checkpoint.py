"""Part ``checkpoint``: a checkpoint moves between machines (the other hash-grid backend, a machine
without CUDA)."""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List

import torch

from sp_plugins.cli.gpu_check.budget import Deadline, Sizes
from sp_plugins.cli.gpu_check.machine import tcnn_reason
from sp_plugins.cli.gpu_check.report import failure, log
from sp_plugins.cli.gpu_check.runs import train_in_process


def check_checkpoint(device, sizes: Sizes, out: Path, deadline: Deadline, artifacts: dict) -> dict:
    """Part ``checkpoint``: the ``sp-neus-hashgrid`` checkpoint of the runs part resumed under the
    other hash-grid backend (weights and Adam moments), then evaluated by ``ns-eval`` with CUDA hidden."""
    saved = artifacts.get("checkpoint")
    if saved is None:
        return {"status": "skipped", "reason": "no sp-neus-hashgrid checkpoint: the runs part did not train it (see runs)"}
    result: dict = {"trained_with": saved["backend"], "skipped": []}
    other = "torch" if saved["backend"] == "tcnn" else None
    if other is None:
        result["skipped"].append(f"the other backend: none here ({tcnn_reason(device)}): resumed under the same one")
    late = deadline.too_late(20)
    if late:
        result["skipped"].append(f"resume: {late}")
    else:
        log(f"checkpoint: resume under the {other or saved['backend']} backend ...")
        config = copy.deepcopy(saved["config"])
        config.load_dir = saved["dir"]
        config.output_dir = out / "resumed"
        try:
            trainer, step, losses = train_in_process(config, device, torch_grid=other == "torch")
            start = trainer._start_step
            for i in range(start, start + sizes.resume_steps):
                step(i)
            grid = [m for m in trainer.pipeline.model.modules() if type(m).__name__ == "HashGrid"]
            param = next(grid[0].parameters())
            moments = [s.get("exp_avg") for opt in trainer.optimizers.optimizers.values() for p, s in opt.state.items() if p is param]
            result["resume"] = {
                "continued_from_step": start, "backend": grid[0].backend, "other_backend": grid[0].backend != saved["backend"], "finite": bool(torch.isfinite(torch.stack(losses)).all()),
                "adam_moments_match": bool(moments and moments[0] is not None and moments[0].shape == param.shape),
            }
            result["resume"]["ok"] = (result["resume"]["finite"] and result["resume"]["adam_moments_match"]
                                      and start == saved["step"] + 1 and (other is None or result["resume"]["other_backend"]))
        except Exception as exc:
            result["resume"] = {"ok": False, "error": failure(exc)}
    if not sizes.eval_on_cpu:
        result["skipped"].append("ns-eval with CUDA hidden: --quick")
    elif deadline.too_late(60):
        result["skipped"].append(f"ns-eval with CUDA hidden: {deadline.too_late(60)}")
    else:
        log("checkpoint: ns-eval with CUDA hidden ...")
        config_path = saved["config"].get_base_dir() / "config.yml"
        metrics = out / "eval_on_cpu.json"
        cmd = [_tool("ns-eval"), "--load-config", str(config_path), "--output-path", str(metrics)]
        env = dict(os.environ, CUDA_VISIBLE_DEVICES="", OMP_WAIT_POLICY="PASSIVE")
        result["eval_on_cpu"] = run_command(cmd, env, timeout=max(deadline.remaining() - 20, 10))
        if metrics.is_file():
            result["eval_on_cpu"]["results"] = json.loads(metrics.read_text()).get("results")
        result["eval_on_cpu"]["ok"] = result["eval_on_cpu"]["returncode"] == 0 and metrics.is_file()
    done = [result[k]["ok"] for k in ("resume", "eval_on_cpu") if k in result]
    cut = any("deadline" in s for s in result["skipped"])
    result["status"] = "ok" if all(done) and not cut else "failed"
    return result


def _tool(name: str) -> str:
    return shutil.which(name) or str(Path(sys.executable).parent / name)


def run_command(cmd: List[str], env: Dict[str, str], timeout: float) -> dict:
    """Run ``cmd``: its exit status and seconds, and its output's tail when it failed."""
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
        code, output = proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as exc:
        code, output = None, f"timed out after {timeout:.0f} s\n{exc.stdout or ''}{exc.stderr or ''}"
    result = {"command": " ".join(cmd), "returncode": code, "seconds": time.perf_counter() - start}
    if code != 0:
        result["output_tail"] = str(output)[-3000:]
    return result
