"""Silence the host stack's known deprecation and CPU warnings, and only those.

nerfstudio 1.1.5 on torch 2.14 prints a dozen warnings that the user can do nothing about (the
host calls APIs torch has deprecated since, or CUDA-only helpers on a CPU). Each filter below
names the exact message and the host module the warning is attributed to, so a warning raised
by sp_plugins itself (module ``sp_plugins.*``) or any other message is never hidden.

- Our console scripts (``sp-fit``, ``sp-demo``, ``sp-scene``, ``sp-bench``, ``sp-export-mesh``)
  call :func:`filter_host_warnings` first: we own the process.
- ``sp-train`` installs them first thing. Under ``ns-train`` / ``ns-eval`` / ``ns-export`` /
  ``ns-render`` they go in when one of *our* methods is built (its data manager or model), never
  when nerfstudio merely discovers our method configs: a nerfacto user sees every warning
  nerfstudio and torch print, as without sp-plugins. Warnings raised before our method is built
  (nerfstudio's imports, ``torch.jit.script``) still print once.
- ``SP_HOST_WARNINGS=1`` in the environment keeps every warning.
"""

from __future__ import annotations

import os
import warnings

HOST_WARNINGS: tuple[tuple[type[Warning], str, str], ...] = (
    # (category, message regex, module regex): why it is not actionable
    # nerfstudio's Cameras index with lists; torch 2.9+ deprecates it (per call site, each once)
    (UserWarning, r"Using a non-tuple sequence for multidimensional indexing is deprecated", r"nerfstudio\.cameras\.cameras"),
    # nerfstudio's writer calls float() on a loss that still requires grad
    (UserWarning, r"Converting a tensor with requires_grad=True to a scalar", r"nerfstudio\.utils\.writer"),
    # nerfstudio's trainer builds torch.cuda.amp.GradScaler; on a CPU torch disables it and says so
    (FutureWarning, r"`torch\.cuda\.amp\.GradScaler\(args\.\.\.\)` is deprecated", r"nerfstudio\.engine\.trainer"),
    (UserWarning, r"torch\.cuda\.amp\.GradScaler is enabled, but CUDA is not available", r"torch\.cuda\.amp\.grad_scaler"),
    # nerfstudio's activations and field components (imported by ours before nerfstudio's own import sometimes)
    (FutureWarning, r"`torch\.cuda\.amp\.custom_(fwd|bwd)\(args\.\.\.\)` is deprecated", r"nerfstudio\..*"),
    (FutureWarning, r"`torch\.jit\.script` is deprecated", r"torch\.jit\._script"),
    # nerfstudio's data managers ask for 4 loader workers per device whatever the core count
    (UserWarning, r"This DataLoader will create \d+ worker processes in total", r"torch\.utils\.data\.dataloader"),
    # viser (nerfstudio's viewer) imports websockets' legacy API
    (DeprecationWarning, r"websockets\.", r"websockets\..*"),
)


def filter_host_warnings() -> bool:
    """Install the filters (idempotent); False when ``SP_HOST_WARNINGS=1`` keeps them all."""
    if os.environ.get("SP_HOST_WARNINGS", "") == "1":
        return False
    for category, message, module in HOST_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)
    return True
