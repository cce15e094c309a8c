"""The machine: what ``nvidia-smi`` and torch see, why a CUDA device cannot be checked, whether
tiny-cuda-nn runs."""

from __future__ import annotations

import platform
import shutil
import subprocess
import time
from importlib.metadata import version
from typing import Optional

import torch

from sp_plugins.cli.gpu_check.budget import CPU_COMMAND
from sp_plugins.encodings.hashgrid import _import_tcnn


def nvidia_driver() -> Optional[str]:
    """``name, driver`` per GPU from ``nvidia-smi`` (None when it is not installed)."""
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return None
    try:
        proc = subprocess.run([exe, "--query-gpu=name,driver_version", "--format=csv,noheader"], capture_output=True,
                              text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"nvidia-smi failed: {exc}"
    return (proc.stdout.strip() or proc.stderr.strip() or f"nvidia-smi exit {proc.returncode}").replace("\n", "; ")


def cuda_problem(device: str) -> Optional[str]:
    """Why ``device`` (a CUDA device) cannot be checked here, in one line; None when it can."""
    if torch.version.cuda is None:
        return (f"torch {torch.__version__} is a CPU-only build: no GPU can be checked; install a CUDA build of torch, "
                f"or check the CPU paths only: {CPU_COMMAND}")
    driver = nvidia_driver()
    seen = f"NVIDIA driver: {driver}" if driver else "nvidia-smi not found (no NVIDIA driver installed?)"
    if not torch.cuda.is_available():
        return (f"torch {torch.__version__} is a CUDA {torch.version.cuda} build but sees no CUDA device ({seen}); an NVIDIA "
                f"driver too old for CUDA {torch.version.cuda} hides the GPU from it: update the driver, or install a torch "
                f"build for the driver's CUDA version; on a machine without a GPU, check the CPU paths: {CPU_COMMAND}")
    dev = torch.device(device)
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        return f"--device {device}: this machine has {torch.cuda.device_count()} CUDA device(s) ({seen})"
    return None


def machine_report(device) -> dict:
    """What ran the check (the report's ``machine``): Python, torch and its CUDA, the GPU, the packages."""
    info = {"python": platform.python_version(), "torch": torch.__version__, "torch_cuda": torch.version.cuda,
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "device": str(device), "nvidia_smi": nvidia_driver()}
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        info.update(gpu=props.name, gpu_memory_gib=round(props.total_memory / 2**30, 1), capability=f"{props.major}.{props.minor}")
    try:
        info["tinycudann"] = version("tinycudann")
    except Exception:  # not installed, or installed without metadata
        info["tinycudann"] = None
    for name in ("nerfstudio", "sp-plugins"):
        try:
            info[name] = version(name)
        except Exception:
            info[name] = None
    return info


def tcnn_reason(device) -> Optional[str]:
    """Why tiny-cuda-nn cannot run on ``device`` (None when it can)."""
    if device.type != "cuda":
        return f"tiny-cuda-nn runs on CUDA only (--device {device})"
    if _import_tcnn() is None:
        return "tinycudann does not import (install it: docs/guides/gpu-check.md)"
    return None
