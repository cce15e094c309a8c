"""Run trials on Ray Tune: a local Ray on the free cores by default, or an existing cluster.

Each trial is one Tune trial of a grid search over the *pending* trials, with its own CPU / GPU
resources, so Ray decides how many run at once and where. Resuming is done by our results
store, not by ``Tuner.restore``: every trial writes ``result.json`` into a folder named by a
hash of its command line, and the sweep hands Ray only trials without one. That survives a
killed driver (Tune's experiment snapshot is periodic), and a sweep may grow (new grid values,
seeds) between runs, which a restored Tuner cannot.

Local Ray runs without dashboard, usage statistics or worker log forwarding, in a short-lived
temporary folder that is removed, with the cluster, when the sweep ends.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, List, Optional

from sp_plugins.sweeps.spec import SpecError
from sp_plugins.sweeps.trial import run_trial

QUIET_RAY_ENV = {
    "RAY_USAGE_STATS_ENABLED": "0",  # no usage report (and no network)
    "RAY_DEDUP_LOGS": "0",
    "RAY_CHDIR_TO_TRIAL_DIR": "0",  # trials run in the sweep's working directory
    "TUNE_DISABLE_AUTO_CALLBACK_LOGGERS": "1",  # no CSV / JSON / TensorBoard loggers per trial: our store has the results
    "RAY_AIR_NEW_OUTPUT": "0",
    "TUNE_WARN_EXCESSIVE_EXPERIMENT_CHECKPOINT_SYNC_THRESHOLD_S": "100000",
    # a loaded 2-core machine took over a minute to start a worker (import ray); Ray's 60 s limit
    # then dropped the worker and the sweep waited forever
    "RAY_worker_register_timeout_seconds": "900",
    "RAY_agent_register_timeout_ms": "900000",
    # a local Ray's workers at this command's priority, not niceness 15: on a busy machine a niced
    # worker took minutes just to start (import ray) before its trial could run
    "RAY_worker_niceness": "0",
}


def _trainable(config: dict) -> None:
    from ray import tune

    result = run_trial(config["trial"])
    scalars = {k: v for k, v in result["metrics"].items() if isinstance(v, (int, float)) and v is not None}
    tune.report({**scalars, "ok": int(result["status"] == "ok")})


def _progress_callback(total: int, log: Callable[[str], None]):
    from ray import tune

    class Progress(tune.Callback):
        """One line per finished trial: how far the sweep is and what the trial gave."""

        def __init__(self) -> None:
            self.done = 0
            self.start = time.time()

        def _line(self, trial, what: str) -> None:
            self.done += 1
            elapsed = time.time() - self.start
            eta = elapsed / self.done * (total - self.done)
            log(f"[sp-sweep] {self.done}/{total} {what}: {trial.config['trial']['label']} "
                f"({elapsed / 60:.1f} min so far, ~{eta / 60:.1f} min left)")

        def on_trial_complete(self, iteration, trials, trial, **info) -> None:
            r = trial.last_result or {}
            if r.get("ok"):
                shown = [f"{k} {r[k]:.4g}" for k in ("psnr", "ssim", "chamfer", "fscore", "sound") if k in r]
                self._line(trial, "done " + ", ".join(shown))
            else:
                self._line(trial, "FAILED")

        def on_trial_error(self, iteration, trials, trial, **info) -> None:
            self._line(trial, "CRASHED")

    return Progress()


def _init_local(ray, num_cpus: Optional[int], num_gpus: Optional[int], temp_dir: Path) -> None:
    import logging

    ray.init(num_cpus=num_cpus, num_gpus=num_gpus or 0, include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING, _temp_dir=str(temp_dir), object_store_memory=100 * 2**20)


def run_on_ray(
    trials: Callable[[], List[dict]],
    *,
    storage: Path,
    address: Optional[str] = None,
    num_cpus: Optional[int] = None,
    num_gpus: Optional[int] = None,
    cpus_per_trial: float = 1.0,
    gpus_per_trial: float = 0.0,
    temp_dir: Optional[Path] = None,
    log: Callable[[str], None] = print,
) -> List[dict]:
    """Run the trials ``trials()`` gives once Ray is up (dicts for :func:`sp_plugins.sweeps.trial.run_trial`);
    returns, for trials that Ray itself lost (worker crash), ``{"key", "error"}`` so the caller can
    record them. A cluster that does not answer is a :class:`SpecError` (one line)."""
    for k, v in QUIET_RAY_ENV.items():
        os.environ.setdefault(k, v)
    import logging

    import ray
    from ray import tune

    logging.getLogger("ray.tune.analysis.experiment_analysis").setLevel(logging.ERROR)  # we keep our own results
    # without ray[default] (aiohttp, ...) Ray logs its dashboard's failed start as errors, though it is not needed
    logging.getLogger("ray._private.services").setLevel(logging.CRITICAL)
    own_temp = None
    if address:
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
        except ConnectionError as err:
            raise SpecError(f"--address {address}: no Ray cluster answered ({str(err).split('. ')[0]}); start one "
                            "(ray start --head) or leave --address out to run on a local Ray") from None
    else:
        # a short path: Ray's socket paths must fit in 107 characters
        own_temp = Path(tempfile.mkdtemp(prefix="spray-", dir="/tmp" if os.path.isdir("/tmp") else None)) \
            if temp_dir is None else Path(temp_dir)
        own_temp.mkdir(parents=True, exist_ok=True)
        try:
            _init_local(ray, num_cpus, num_gpus, own_temp)
        except BaseException:
            _stop_leftovers(own_temp)
            shutil.rmtree(own_temp, ignore_errors=True)
            raise
    lost = []
    try:
        items = trials()
        # a local sweep's trials run at this command's niceness, not Ray's worker niceness (15)
        niceness = None if address or not hasattr(os, "getpriority") else os.getpriority(os.PRIO_PROCESS, 0)
        for t in items:
            t["cpus"], t["gpus"], t["niceness"] = cpus_per_trial, gpus_per_trial, niceness
        tuner = tune.Tuner(
            tune.with_resources(_trainable, {"cpu": cpus_per_trial, "gpu": gpus_per_trial}),
            param_space={"trial": tune.grid_search(items)},
            # reuse_actors: a trial is a subprocess (run_trial), so its worker holds no state between trials; a
            # new worker per trial spent 8-15 s on a 2-core machine importing ray before the trial started
            tune_config=tune.TuneConfig(trial_dirname_creator=lambda tr: tr.config["trial"]["key"],
                                        trial_name_creator=lambda tr: tr.config["trial"]["key"], reuse_actors=True),
            run_config=tune.RunConfig(
                name=time.strftime("run-%Y%m%d-%H%M%S"), storage_path=str(Path(storage).resolve()), verbose=0,
                failure_config=tune.FailureConfig(max_failures=0), callbacks=[_progress_callback(len(items), log)],
            ),
        )
        grid = tuner.fit()
        for result in grid:
            if result.error is not None:
                lost.append({"key": result.config["trial"]["key"], "error": f"ray: {type(result.error).__name__}: {result.error}"[:400]})
    finally:
        ray.shutdown()
        if own_temp is not None:
            _stop_leftovers(own_temp)
            shutil.rmtree(own_temp, ignore_errors=True)
    return lost


def _stop_leftovers(temp_dir: Path, grace: float = 10.0) -> None:
    """Stop processes of *this* local Ray that outlive ``ray.shutdown()`` (on a loaded machine
    its dashboard and runtime-env agents can): those whose command line names our temp folder."""
    import psutil

    mark = str(temp_dir)
    mine = []
    for proc in psutil.process_iter(["pid", "cmdline"]):
        try:
            if proc.pid != os.getpid() and any(mark in part for part in (proc.info["cmdline"] or [])):
                mine.append(proc)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    for proc in mine:
        try:
            proc.terminate()
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(mine, timeout=grace)
    for proc in alive:
        try:
            proc.kill()
        except psutil.NoSuchProcess:
            pass
