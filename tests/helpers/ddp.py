"""Run nerfstudio's own multi-process training on the CPU: two processes over a gloo process group.

``ns-train --machine.num-devices 2`` goes through ``nerfstudio.scripts.train.launch``, which spawns one
``_distributed_worker`` per device; that worker asserts CUDA (``torch.cuda.is_available()``, then
``num_devices <= torch.cuda.device_count()``), initialises the process group (gloo for a non-CUDA
device type) and calls ``train_loop(local_rank, world_size, config, global_rank)``. On a machine
without CUDA the launcher stops at its first assertion ("cuda is not available"), so this harness
starts the processes itself and does what the worker does after its assertions: the same process
group (gloo, ``tcp://127.0.0.1:<free port>``, ``comms.LOCAL_PROCESS_GROUP``), then nerfstudio's own
``train_loop``, then ``comms.synchronize()``.

The CUDA-only arguments nerfstudio passes inside training are both in
``VanillaPipeline.__init__`` (nerfstudio 1.1.5, ``pipelines/base_pipeline.py``)::

    self._model = DDP(self._model, device_ids=[local_rank], find_unused_parameters=True)
    dist.barrier(device_ids=[local_rank])

- ``DDP(..., device_ids=[local_rank])``: torch refuses it for a module on the CPU ("device_ids and
  output_device arguments only work with single-device/multiple-device GPU modules or CPU modules"; a
  CPU module needs ``device_ids=None``). This is the one adaptation: in the child processes only,
  the pipeline module's ``DDP`` name is a subclass of ``DistributedDataParallel`` whose only
  change is ``device_ids=None`` when the module is on the CPU; everything else
  (``find_unused_parameters=True``, the gradient all-reduce, the buffer broadcast) is torch's.
- ``dist.barrier(device_ids=[local_rank])``: gloo on the CPU accepts it (torch 2.14: the barrier runs
  on ``cpu:<rank>``), so it is left as nerfstudio calls it.

Nothing else is changed: the trainer, the pipeline, the data manager (each rank seeded by
``train_loop`` with ``--machine.seed + rank``, so each samples its own rays) and our models are the
ones ``ns-train`` runs.

The processes: one launcher subprocess imports nerfstudio once and forks one process per rank (each
logging to ``rank<r>.log``); each rank trains the runs (one saved ``config.yml`` each) one after the
other in the same process group. What each rank records, per run:

- ``status``: ``trained``, or ``refused`` with the exception's type and message;
- per step: the loss, alpha and scalar metrics, and (in ``<run>/rank<r>-step<s>.pt``) every parameter
  and buffer of the model after that step's optimizer step;
- the noise: the first values (and the shape) of the first draw of the SP noise, captured at
  ``sample_noise``, where every perturbation draws; the number of draws; the seeds of the
  preconditioner's generators;
- whether the pipeline's model was the ``DistributedDataParallel`` wrapper (and its ``device_ids``),
  and the perturbed-call counters of the fields (SP reached a field through the wrapper).

``python tests/helpers/ddp.py SPEC`` is the launcher; tests call :func:`run_ddp`.
"""

from __future__ import annotations

import importlib
import json
import os
import socket
import subprocess
import sys
import time
import traceback
from datetime import timedelta
from pathlib import Path
from typing import Dict, List

ROOT = Path(__file__).resolve().parents[2]
NOISE_VALUES = 256  # values of the first noise draw each rank reports


# -- parent side --------------------------------------------------------------------------------
def free_port() -> int:
    """A free TCP port on the loopback interface (as nerfstudio's ``_find_free_port``)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def run_ddp(configs: Dict[str, object], workdir: Path, *, world_size: int = 2, timeout: float = 600,
            pg_timeout: float = 120) -> Dict[str, List[dict]]:
    """Train each ``TrainerConfig`` in ``configs`` (name -> config) with nerfstudio's ``train_loop`` in
    ``world_size`` CPU processes; returns name -> one record per rank (see the module docstring).

    Each config is saved as ``ns-train --machine.num-devices <world_size>`` would save it. The runs are
    trained in order by the same processes. Fails with the launcher's and the ranks' logs when a
    process fails (a refusal is recorded, not a failure) or the whole takes longer than ``timeout``
    seconds (a rank stuck in a collective gives up after ``pg_timeout``)."""
    from nerfstudio.engine.trainer import TrainerConfig

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    runs = []
    for name, config in configs.items():
        config.machine.num_devices = world_size  # what the multi-device command line saves
        config.machine.device_type = "cpu"
        # nerfstudio's own save_config: the command line's checks (ours run before ns-train saves) are not
        # this harness's business, and a run resumed from an earlier run here names a folder not yet written
        TrainerConfig.save_config(config)
        record = workdir / name
        record.mkdir(exist_ok=True)
        runs.append({"name": name, "config": str(config.get_base_dir() / "config.yml"), "record": str(record)})
    spec = workdir / "spec.json"
    spec.write_text(json.dumps({"world_size": world_size, "port": free_port(), "pg_timeout": pg_timeout, "runs": runs}))
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE",
               PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    with open(workdir / "launcher.log", "w") as log:
        proc = subprocess.Popen([sys.executable, __file__, str(spec)], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()  # its ranks die with it (PR_SET_PDEATHSIG)
            proc.wait()

    def logs() -> str:
        tails = [f"--- launcher\n{(workdir / 'launcher.log').read_text()[-3000:]}"]
        for r in range(world_size):
            path = workdir / f"rank{r}.log"
            tails.append(f"--- rank {r}\n{path.read_text()[-4000:] if path.exists() else '(no log)'}")
        return "\n".join(tails)

    assert proc.returncode == 0, f"the launcher exited with {proc.returncode}\n{logs()}"
    results = {}
    for run in runs:
        results[run["name"]] = [json.loads((Path(run["record"]) / f"rank{r}.json").read_text()) for r in range(world_size)]
    return results


def step_state(workdir: Path, name: str, rank: int, step: int) -> dict:
    """``{"params": {name: tensor}, "buffers": {name: tensor}}`` of rank ``rank`` after ``step``."""
    import torch

    return torch.load(Path(workdir) / name / f"rank{rank}-step{step}.pt", map_location="cpu", weights_only=True)


# -- child side ---------------------------------------------------------------------------------
def adapt_cuda_only_arguments() -> None:
    """The pipeline's ``DDP(model, device_ids=[local_rank], ...)`` with ``device_ids=None`` for a CPU
    module (what torch requires there); every other argument as nerfstudio passes it."""
    import nerfstudio.pipelines.base_pipeline as base_pipeline
    from torch.nn.parallel import DistributedDataParallel

    class DDP(DistributedDataParallel):  # a subclass: the pipeline's isinstance(..., DDP) checks still hold
        def __init__(self, module, *args, device_ids=None, **kwargs):
            if all(p.device.type == "cpu" for p in module.parameters()):
                device_ids = None
            super().__init__(module, *args, device_ids=device_ids, **kwargs)

    base_pipeline.DDP = DDP


def child(spec_path: str, rank: int) -> None:
    import torch

    torch.set_num_threads(1)
    import torch.distributed as dist
    import yaml
    from nerfstudio.engine.trainer import Trainer
    from nerfstudio.scripts.train import train_loop
    from nerfstudio.utils import comms
    from torch.nn.parallel import DistributedDataParallel

    from sp_plugins.adapter.field import PreconditionerHandle

    spec = json.loads(Path(spec_path).read_text())
    world_size = spec["world_size"]
    # what nerfstudio's _distributed_worker does after its CUDA assertions
    dist.init_process_group(backend="gloo", init_method=f"tcp://127.0.0.1:{spec['port']}", world_size=world_size,
                            rank=rank, timeout=timedelta(seconds=spec["pg_timeout"]))
    comms.LOCAL_PROCESS_GROUP = dist.new_group(list(range(world_size)))
    adapt_cuda_only_arguments()

    current: dict = {}

    # every perturbation draws its noise through this module's sample_noise (the package's
    # ``sp_plugins.core.perturb`` attribute is the function of that name, hence importlib)
    perturb_module = importlib.import_module("sp_plugins.core.perturb")

    sample_noise = perturb_module.sample_noise

    def recording_noise(*args, **kwargs):
        eps = sample_noise(*args, **kwargs)
        if current.get("noise") is None:
            current["noise"] = [float(v) for v in eps.detach().flatten()[:NOISE_VALUES].cpu()]
            current["noise_shape"] = list(eps.shape)
        current["draws"] = current.get("draws", 0) + 1
        return eps

    perturb_module.sample_noise = recording_noise

    train_iteration = Trainer.train_iteration

    def recording_iteration(self, step):
        loss, loss_dict, metrics = train_iteration(self, step)
        model = self.pipeline.model
        current["ddp"] = isinstance(self.pipeline._model, DistributedDataParallel)
        current["ddp_device_ids"] = getattr(self.pipeline._model, "device_ids", "n/a")
        torch.save({"params": {k: v.detach().cpu().clone() for k, v in model.named_parameters()},
                    "buffers": {k: v.detach().cpu().clone() for k, v in model.named_buffers()}},
                   Path(current["record"]) / f"rank{rank}-step{step}.pt")
        sp = getattr(model, "sp", None)
        scalars = {k: float(v) for k, v in metrics.items() if not isinstance(v, torch.Tensor) or v.numel() == 1}
        current["steps"].append({"step": step, "loss": float(loss.detach()), "metrics": scalars,
                                 "alpha": None if sp is None else float(sp.alpha)})
        return loss, loss_dict, metrics

    Trainer.train_iteration = recording_iteration

    for run in spec["runs"]:
        current.clear()
        current.update(record=run["record"], steps=[], status="trained", error=None)
        config = yaml.load(Path(run["config"]).read_text(), Loader=yaml.Loader)
        holder: dict = {}
        setup = Trainer.setup

        def keep_trainer(self, *args, **kwargs):  # the trainer train_loop builds, to read its model after
            holder["trainer"] = self
            return setup(self, *args, **kwargs)

        Trainer.setup = keep_trainer
        started = time.monotonic()
        try:
            train_loop(rank, world_size, config, rank)  # one machine: local rank = global rank
        except Exception as err:  # noqa: BLE001  (a refusal: recorded for the test, then the next run)
            current["status"] = "refused"
            current["error"] = {"type": f"{type(err).__module__}.{type(err).__qualname__}", "message": str(err),
                                "traceback": traceback.format_exc()}
        finally:
            Trainer.setup = setup
        current["seconds"] = time.monotonic() - started
        trainer = holder.get("trainer")
        model = getattr(getattr(trainer, "pipeline", None), "model", None)
        if model is not None:
            sp = getattr(model, "sp", None)
            current["seeds"] = sorted(g.initial_seed() for g in getattr(sp, "_generators", {}).values())
            current["perturbed_calls"] = sum(
                h.perturbed_calls for h in (getattr(m, "sp_handle", None) for m in model.modules())
                if isinstance(h, PreconditionerHandle))
        result = {k: v for k, v in current.items() if k != "record"}
        Path(run["record"], f"rank{rank}.json").write_text(json.dumps(result))
        dist.barrier()  # both ranks done with this run before the next starts

    comms.synchronize()
    dist.destroy_process_group()


def launcher(spec_path: str) -> int:
    """Import nerfstudio once, then fork one process per rank (each with its own log file); the
    exit status is 0 when every rank ended with 0. A rank that fails makes the others stop."""
    import ctypes
    import signal

    import torch

    torch.set_num_threads(1)
    import nerfstudio.scripts.train  # noqa: F401  (imported once, shared by the forked ranks)

    import sp_plugins.nerfstudio.runs  # noqa: F401

    spec = json.loads(Path(spec_path).read_text())
    workdir = Path(spec_path).parent
    pids = {}
    for rank in range(spec["world_size"]):
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG: die with the launcher
                fd = os.open(workdir / f"rank{rank}.log", os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
                os.dup2(fd, 1)
                os.dup2(fd, 2)
                child(spec_path, rank)
                code = 0
            except BaseException:  # noqa: BLE001
                traceback.print_exc()
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(code)
        pids[pid] = rank
    failed = []
    while pids:
        pid, status = os.wait()
        rank = pids.pop(pid)
        if status != 0:
            failed.append(rank)
            print(f"rank {rank} ended with status {status:#x}", flush=True)
            for other in pids:  # it would wait for the failed rank in a collective until the timeout
                os.kill(other, signal.SIGKILL)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(launcher(sys.argv[1]))
