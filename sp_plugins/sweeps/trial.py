"""Run one trial as a user would: ``ns-train`` (then ``ns-eval``) or ``sp-fit`` in a subprocess.

Each trial owns a folder named by its key: ``trial.json`` (grid point, SP side, seed, command),
``stdout.log`` / ``stderr.log`` and, once it has ended, ``result.json`` with ``status`` ("ok" or
"failed"), the error line of a failure, the ``device`` it ran on (cpu / cuda) and the metrics:

- ns-train: ``psnr``, ``ssim`` (and ``lpips`` when available) on the test split from ns-eval's
  JSON, ``train_seconds``, ``eval_seconds``;
- sp-fit: the scalars of its ``metrics.json`` (``chamfer``, ``fscore``, ``normal_consistency``,
  ``area_ratio``, ``negative_fraction``, ``seconds``, ...) and, for point-cloud and SDF fits
  against a mesh, ``sound`` (1/0, see :mod:`sp_plugins.sweeps.soundness`).

``result.json`` is written last and atomically, so its presence means the trial has finished:
this is what lets a restarted sweep skip it.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

from sp_plugins.sweeps.soundness import is_sound, true_negative_fraction

RESULT = "result.json"
TRIAL = "trial.json"
FIT_METRICS = ("chamfer", "clean_chamfer", "fscore", "clean_fscore", "normal_consistency", "area_ratio",
               "negative_fraction", "components", "psnr", "seconds", "seconds_per_step", "final_loss", "steps")


def program_path(name: str) -> str:
    """A console script of this environment (next to the interpreter), else from PATH."""
    local = Path(sys.executable).parent / name
    return str(local) if local.exists() else (shutil.which(name) or name)


def _die_with_parent() -> None:
    """Linux: the child gets SIGTERM when the worker that started it dies, so an interrupted
    sweep leaves no training processes behind."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def _child_setup(niceness: Optional[int]):
    """What the trial's process does before it starts: die with its parent and, when given, run at
    ``niceness``. Ray starts its workers at niceness 15; without this a local sweep's trials yield
    the CPU to every other job on the machine (measured: 9% of a core each beside three ordinary
    jobs). Lowering the niceness needs the right to (root or CAP_SYS_NICE); without it the trial
    keeps Ray's."""

    def setup() -> None:
        if sys.platform.startswith("linux"):
            _die_with_parent()
        if niceness is not None:
            try:
                os.setpriority(os.PRIO_PROCESS, 0, niceness)
            except (OSError, AttributeError):
                pass

    return setup


def _error_line(stderr: Path, returncode: int) -> str:
    """The last line that says what went wrong (our CLIs print one ``...: error: ...`` line)."""
    lines = [ln.strip() for ln in stderr.read_text(errors="replace").splitlines() if ln.strip()] if stderr.exists() else []
    for ln in reversed(lines):
        if ": error:" in ln or "Error" in ln or "error" in ln.lower():
            return ln[:400]
    return (lines[-1][:400] if lines else "") or f"exit status {returncode}"


def _run(argv: List[str], cwd: str, env: dict, folder: Path, timeout: Optional[float], tag: str,
         niceness: Optional[int] = None) -> tuple[int, float, Path]:
    out, err = folder / f"{tag}stdout.log", folder / f"{tag}stderr.log"
    start = time.perf_counter()
    with open(out, "w") as fo, open(err, "w") as fe:
        proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=fo, stderr=fe, stdin=subprocess.DEVNULL,
                                preexec_fn=_child_setup(niceness) if os.name == "posix" else None)
        try:
            code = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            fe.write(f"\nsp-sweep: error: timed out after {timeout:.0f} s\n")
            code = -9
        except BaseException:  # the trial was cancelled: do not leave the child running
            proc.kill()
            proc.wait()
            raise
    return code, time.perf_counter() - start, err


def _write_result(folder: Path, result: dict) -> None:
    tmp = folder / (RESULT + ".tmp")
    tmp.write_text(json.dumps(_finite(result), indent=1) + "\n")
    tmp.replace(folder / RESULT)


def _finite(obj):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    return obj


def _env(threads: int) -> dict:
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = str(max(1, threads))
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def _has_flag(argv: List[str], flag: str) -> bool:
    return any(a == flag or a.startswith(flag + "=") for a in argv)


def ns_train_argv(argv: List[str], folder: Path, data_args: int, gpus: float) -> List[str]:
    """Insert the output flags (and CPU / tensorboard defaults the spec did not set) before the
    dataparser subcommand, which takes the last ``data_args`` arguments."""
    head, tail = (argv[: len(argv) - data_args], argv[len(argv) - data_args:]) if data_args else (argv, [])
    extra = ["--output-dir", str(folder / "train"), "--experiment-name", "trial", "--timestamp", "run"]
    if not _has_flag(head, "--machine.device-type"):
        extra += ["--machine.device-type", "cuda" if gpus > 0 else "cpu"]
    if not _has_flag(head, "--vis"):
        extra += ["--vis", "tensorboard"]
    return [program_path(head[0]), *head[1:], *extra, *tail]


def run_trial(trial: dict) -> dict:
    """Run ``trial`` (a dict: key, argv, folder, cwd, data_args, cpus, gpus, timeout, eval) and
    write its ``result.json``; returns that result."""
    folder = Path(trial["folder"])
    folder.mkdir(parents=True, exist_ok=True)
    (folder / RESULT).unlink(missing_ok=True)
    argv: List[str] = list(trial["argv"])
    env = _env(int(math.ceil(trial.get("cpus", 1))))
    timeout = trial.get("timeout")
    result: Dict = {"key": trial["key"], "params": trial["params"], "sp": trial["sp"], "seed": trial["seed"],
                    "device": trial.get("device", "cpu"), "status": "failed", "error": None, "metrics": {}}
    try:
        if argv[0] == "ns-train":
            _ns_train(trial, argv, folder, env, timeout, result)
        elif argv[0] == "sp-fit":
            _sp_fit(trial, argv, folder, env, timeout, result)
        else:
            result["error"] = f"unknown program {argv[0]!r}"
    except Exception as err:  # a trial that cannot even be run is a failed trial, not a failed sweep
        result["status"], result["error"] = "failed", f"{type(err).__name__}: {err}"[:400]
    _write_result(folder, result)
    return result


def _ns_train(trial: dict, argv: List[str], folder: Path, env: dict, timeout, result: dict) -> None:
    cmd = ns_train_argv(argv, folder, trial.get("data_args", 0), trial.get("gpus", 0))
    (folder / "command.txt").write_text(" ".join(cmd) + "\n")
    code, seconds, err = _run(cmd, trial["cwd"], env, folder, timeout, "", trial.get("niceness"))
    result["metrics"]["train_seconds"] = seconds
    if code != 0:
        result["error"] = _error_line(err, code)
        return
    configs = sorted((folder / "train").glob("**/config.yml"))
    if not configs:
        result["error"] = "ns-train finished but wrote no config.yml"
        return
    if not trial.get("eval", True):
        result["status"] = "ok"
        return
    out = folder / "eval.json"
    code, seconds, err = _run([program_path("ns-eval"), "--load-config", str(configs[-1]), "--output-path", str(out)],
                              trial["cwd"], env, folder, timeout, "eval_", trial.get("niceness"))
    result["metrics"]["eval_seconds"] = seconds
    if code != 0 or not out.is_file():
        result["error"] = "ns-eval: " + _error_line(err, code)
        return
    metrics = json.loads(out.read_text()).get("results", {})
    for k in ("psnr", "ssim", "lpips", "psnr_std", "ssim_std"):
        if k in metrics:
            result["metrics"][k] = float(metrics[k])
    result["status"] = "ok"


def _sp_fit(trial: dict, argv: List[str], folder: Path, env: dict, timeout, result: dict) -> None:
    extra = ["--out", str(folder / "fit"), "--overwrite"]
    if not _has_flag(argv, "--quiet"):
        extra.append("--quiet")
    cmd = [program_path("sp-fit"), *argv[1:], *extra]
    (folder / "command.txt").write_text(" ".join(cmd) + "\n")
    code, seconds, err = _run(cmd, trial["cwd"], env, folder, timeout, "", trial.get("niceness"))
    result["metrics"]["wall_seconds"] = seconds
    path = folder / "fit" / "metrics.json"
    if code != 0 or not path.is_file():
        result["error"] = _error_line(err, code)
        return
    metrics = json.loads(path.read_text())
    for k in FIT_METRICS:
        v = metrics.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            result["metrics"][k] = float(v)
        elif k in metrics and v is None:
            result["metrics"][k] = None  # e.g. the Chamfer of an empty mesh
    gt = metrics.get("gt")
    if argv[1] in ("pointcloud", "sdf") and gt and "area_ratio" in metrics and "negative_fraction" in metrics:
        gt_path = Path(gt) if Path(gt).is_absolute() else Path(trial["cwd"]) / gt
        diagonal = float(metrics.get("config", {}).get("frame_diagonal", 1.9))
        truth = true_negative_fraction(gt_path, diagonal)
        result["metrics"]["true_negative_fraction"] = truth
        result["metrics"]["sound"] = float(is_sound(metrics["area_ratio"] or 0.0, metrics["negative_fraction"], truth))
    result["status"] = "ok"
