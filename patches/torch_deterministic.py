"""torch's deterministic kernels while one of our runs trains (registry entry ``torch_deterministic``).

Two runs of the same command at the same seed differed on a CPU with more than one thread: the
backward of advanced indexing (``table[index]``, as in nerfstudio's torch ``HashEncoding``) adds
into the table with ``index_put_(accumulate=True)``, whose CPU kernel sums colliding rows in
thread order. ``torch.use_deterministic_algorithms(True)`` gives it an ordered kernel
(``bench/speed/deterministic_cost.py``, 2 threads: nerfstudio's nerfacto +8% per step, our
``sp-neus-hashgrid`` +0%).

``SP_DETERMINISTIC`` decides, read when the scope opens:

- ``auto`` (the default): deterministic kernels when torch sees no GPU. Our model's hold
  (:func:`sp_plugins.nerfstudio.model.hold_deterministic_kernels`) asks for the scope only on several
  threads (on one every sum has one order already) and not for a model with nerfstudio's torch
  ``HashEncoding``, where the kernels cost more than 5% of a step (it says so once); on a GPU nothing changes;
- ``1``: deterministic kernels on every device: also ``cudnn.deterministic``, no cudnn autotuning
  and ``CUBLAS_WORKSPACE_CONFIG=:4096:8`` where unset (needed by cuBLAS before its first call);
  an op with no deterministic kernel warns once instead of stopping the run (``warn_only``);
- ``0``: nothing changes.

Scope: while our model exists under ``sp-train`` or the host's ``ns-*`` commands, and under
nerfbaselines while our method wrapper exists with ``SP_DETERMINISTIC=1`` (``registry.hold``).
``sp-fit``'s own fields repeat without it; ``sp_plugins.nerfstudio.runs.train`` (the benchmarks' trainer) and
``sp-gpu-check``'s repeat part enter the scope themselves. Building our model in a Python session changes
nothing: call :func:`deterministic_kernels` there. After the scope the
three settings are what they were.
"""

from __future__ import annotations

import contextlib
import os
from typing import Iterator

from sp_plugins.patches.registry import Patch

__all__ = ["PATCH", "deterministic_kernels", "mode", "wanted"]

MODES = ("auto", "1", "0")
TESTED_TORCH_VERSIONS = ("2.14.1",)


def mode() -> str:
    """``SP_DETERMINISTIC`` (default ``auto``), one of :data:`MODES`; ``ValueError`` naming it otherwise."""
    value = os.environ.get("SP_DETERMINISTIC", "auto").strip().lower() or "auto"
    if value not in MODES:
        raise ValueError(f"SP_DETERMINISTIC={value!r}: use auto (the default), 1 or 0")
    return value


def wanted() -> bool:
    """Whether ``SP_DETERMINISTIC`` (default ``auto``) asks for deterministic kernels here."""
    import torch

    asked = mode()
    return asked == "1" or (asked == "auto" and not torch.cuda.is_available())


@contextlib.contextmanager
def deterministic_kernels() -> Iterator[bool]:
    """Deterministic torch kernels for the block where :func:`wanted`; yields whether they are on."""
    import torch

    on = wanted()
    before = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
              torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark)
    if on:
        if torch.cuda.is_available():
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.deterministic = True
        torch.backends.cudnn.benchmark = False
    try:
        yield on
    finally:
        if on:
            torch.use_deterministic_algorithms(before[0], warn_only=before[1])
            torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = before[2], before[3]


def _check(patch: Patch) -> None:
    import torch

    for name in ("use_deterministic_algorithms", "are_deterministic_algorithms_enabled",
                 "is_deterministic_algorithms_warn_only_enabled"):
        patch.expect(callable(getattr(torch, name, None)), f"torch.{name}", "none")


PATCH = Patch(
    name="torch_deterministic",
    host="torch",
    version=", ".join(TESTED_TORCH_VERSIONS),
    changes="torch.use_deterministic_algorithms(True, warn_only=True), cudnn deterministic: runs repeat (SP_DETERMINISTIC)",
    scope_text="our model under sp-train and ns-* while it exists; nerfbaselines' wrapper of ours with SP_DETERMINISTIC=1",
    check=_check,
    enter=deterministic_kernels,
    guarded=(("torch", "use_deterministic_algorithms"), ("torch", "are_deterministic_algorithms_enabled")),
)
