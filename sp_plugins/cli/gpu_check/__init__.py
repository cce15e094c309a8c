"""sp-gpu-check: the first thing to run on a machine with an NVIDIA GPU (8 minutes at most).

    sp-gpu-check                          # CUDA; writes gpu-check/gpu_check.json, exit 1 if anything failed
    sp-gpu-check --require-tcnn           # a missing tinycudann is a failure too
    sp-gpu-check --device cpu --quick     # the parts a CPU can run, small (what the tests run)

It checks what no CPU test can see, each part reporting what it skipped and why:

- ``grid``: tiny-cuda-nn's hash grid against our torch backend from the same weights: outputs and
  input gradients judged by the fraction of points over a relative tolerance (one point the two
  floor into different cells does not fail it), table gradients (tcnn accumulates them in half
  precision), the round trip of the weights, fit and eikonal step times; our grid and SP under
  ``torch.autocast`` (fp16 on CUDA, bf16 on a CPU): positions stay float32 and move. Without
  tinycudann the comparison runs against :mod:`sp_plugins.encodings.tcnn_layout` (tcnn's layout
  read independently) and says so.
- ``runs``: ``neus-hashgrid``, ``sp-neus-hashgrid``, ``sp-neus-hashgrid`` on the torch backend,
  nerfstudio's ``nerfacto``, ``sp-train nerfacto`` and ``sp-nerfacto`` (mixed precision on CUDA as
  configured) trained in this process on a small synthetic scene: steady-state seconds per step
  (CUDA events, after warm-up steps), peak memory from the allocator and the device, and host-device
  syncs per step, ours and the host's (:mod:`sp_plugins.sync_count`, and on CUDA
  ``torch.cuda.set_sync_debug_mode``). From them: the SP overhead per step and torch vs tcnn.
- ``checkpoint``: the ``sp-neus-hashgrid`` checkpoint resumed under the other hash-grid backend
  (weights and Adam moments) and evaluated by ``ns-eval`` with CUDA hidden.
- ``fit``: ``sp-fit pointcloud``'s trainer on the device: seconds per step from its timer against
  the wall clock, no sync of ours per step.

The whole check stops at ``--deadline`` seconds (default 480) counted from the process start;
parts that no longer fit are skipped, naming the deadline, and a part still running then is
reported as cut. A CUDA build of torch that sees no GPU is a failure (exit 1, with the driver and
``torch.version.cuda``), not a skip. Attach ``gpu_check.json`` to GPU bug reports.

One module per part (:mod:`.grid`, :mod:`.runs`, :mod:`.checkpoint`, :mod:`.fit`); the command and
its deadline in :mod:`.harness` and :mod:`.budget`; the machine, the measurements and the report in
:mod:`.machine`, :mod:`.measure` and :mod:`.report`.
"""

from sp_plugins.cli.gpu_check.budget import Deadline, Sizes
from sp_plugins.cli.gpu_check.grid import agreement, compare_points, compare_tables
from sp_plugins.cli.gpu_check.harness import PARTS, entrypoint, main, parse_args
from sp_plugins.cli.gpu_check.report import Report

__all__ = ["PARTS", "Deadline", "Report", "Sizes", "agreement", "compare_points", "compare_tables", "entrypoint", "main",
           "parse_args"]
