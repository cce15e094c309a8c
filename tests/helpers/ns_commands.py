"""Run the real nerfstudio commands (``ns-train``, ``ns-eval``, ``ns-export``, ``ns-render``) in
subprocesses, as a user would, with CPU-sized flags."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import List, Sequence

BIN = Path(sys.executable).parent


def command(name: str) -> str:
    return shutil.which(name, path=str(BIN)) or shutil.which(name) or str(BIN / name)


ENV = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")


def _report(args: Sequence[str], proc: subprocess.CompletedProcess) -> str:
    return f"{' '.join(map(str, args))}\n--- stdout\n{proc.stdout[-3000:]}\n--- stderr\n{proc.stderr[-4000:]}"


def run(args: Sequence[str], timeout: int = 600, server=None) -> subprocess.CompletedProcess:
    """Run ``args`` on one torch thread; fail with the tail of its output when it fails. ``server``: a
    :class:`~tests.helpers.forkserver.ForkServer` (``args[0]`` a console script) runs it in a forked
    child instead of a new interpreter."""
    if server is not None:
        return server.call(list(args))
    proc = subprocess.run(list(args), env=ENV, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, _report(args, proc)
    return proc


RUN_FLAGS = [
    # nerfstudio's default front end, the web viewer, as users run it (a property of ours that
    # raised under its getattr walk stopped every SP run; --vis tensorboard hid it). The one flag added
    # lets the trainer exit after its last step instead of serving until a user closes it.
    "--machine.device-type", "cpu", "--viewer.quit-on-train-completion", "True", "--timestamp", "t",
    "--logging.local-writer.enable", "False", "--pipeline.datamanager.train-num-rays-per-batch", "32",
    "--pipeline.datamanager.eval-num-rays-per-batch", "32",
]

SDF_FLAGS = [
    "--pipeline.model.num-samples", "16", "--pipeline.model.num-samples-importance", "8",
    "--pipeline.model.num-up-sample-steps", "1", "--pipeline.model.num-samples-outside", "8",
    "--pipeline.model.sdf-field.hidden-dim", "32", "--pipeline.model.sdf-field.hidden-dim-color", "32",
    "--pipeline.model.sdf-field.geo-feat-dim", "15", "--pipeline.model.sdf-field.num-levels", "8",
    "--pipeline.model.sdf-field.log2-hashmap-size", "12", "--pipeline.model.sdf-field.max-res", "64",
    "--pipeline.model.eval-num-rays-per-chunk", "512",
    # past the warm-up, so nerfstudio's cosine factor is a numpy scalar (what broke ns-eval)
    "--optimizers.fields.scheduler.warm-up-end", "1", "--optimizers.field-background.scheduler.warm-up-end", "1",
]

NERFACTO_FLAGS = [
    "--pipeline.model.num-nerf-samples-per-ray", "8", "--pipeline.model.num-proposal-samples-per-ray", "8", "8",
    "--pipeline.model.log2-hashmap-size", "12", "--pipeline.model.max-res", "64", "--pipeline.model.hidden-dim", "16",
    "--pipeline.model.camera-optimizer.mode", "off", "--pipeline.model.eval-num-rays-per-chunk", "512",
]


def ns_train(method: str, out: Path, data_args: List[str], *flags: str, steps: int = 2, server=None) -> Path:
    """Train ``method`` for ``steps`` and return the ``config.yml`` it wrote (``server``: see :func:`run`)."""
    proc = run([command("ns-train"), method, *RUN_FLAGS, "--max-num-iterations", str(steps), "--steps-per-save", str(steps),
                "--output-dir", str(out), *flags, *data_args], server=server)
    # the host's per-step deprecation warnings are filtered once our plugin is imported
    assert "non-tuple sequence for multidimensional indexing" not in proc.stderr
    from tests.helpers.viewer import PORT_LINE

    assert PORT_LINE.search(proc.stdout), f"{method} did not train under nerfstudio's viewer:\n{proc.stdout[-2000:]}"
    (config,) = out.glob("**/config.yml")
    assert list(config.parent.glob("nerfstudio_models/step-*.ckpt")), "no checkpoint written"
    return config


def ns_eval_args(config: Path, out: Path) -> List[str]:
    return [command("ns-eval"), "--load-config", str(config), "--output-path", str(out / "eval.json")]


def check_eval(proc: subprocess.CompletedProcess, out: Path) -> dict:
    """What ``ns-eval`` wrote to ``out``: a finite PSNR, and our per-image progress lines."""
    results = json.loads((out / "eval.json").read_text())["results"]
    assert math.isfinite(results["psnr"]), results
    assert "evaluating image 1/" in proc.stderr and "took" in proc.stderr
    return results


def ns_eval(config: Path, out: Path, server=None) -> dict:
    """``ns-eval`` on the checkpoint; returns its results (asserts PSNR is finite)."""
    return check_eval(run(ns_eval_args(config, out), server=server), out)
