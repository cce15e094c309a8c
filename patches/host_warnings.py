"""Silence the host stack's known deprecation and CPU warnings, and only those (registry entry
``host_warnings``).

nerfstudio 1.1.5 on torch 2.x prints a dozen warnings that the user can do nothing about (the
host calls APIs torch has deprecated since, or CUDA-only helpers on a CPU). Each filter below
names the exact message and the host module the warning is attributed to, so a warning raised
by sp_plugins itself (module ``sp_plugins.*``) or any other message is never hidden.

Scope (:mod:`sp_plugins.patches.registry`):

- our console commands (``sp-train``, ``sp-fit``, ``sp-demo``, ``sp-scene``, ``sp-bench``,
  ``sp-export-mesh``, ``sp-sweep``, ``sp-gpu-check``, ``sp-compare``) own their process: there the filters stay
  until it ends (``registry.install_for_process``);
- under nerfstudio's ``ns-*`` commands working on a run of ours they are held by that run's
  objects (``registry.hold``: ``ns-train``'s checked run config; our model and data manager under
  ``ns-eval`` / ``ns-render`` / ``ns-export`` / ``ns-viewer``), and removed with the last of them
  (``warnings.filters`` is the same list object with the entries it had). Building one of our models
  in a Python session, a notebook or a test installs none. A nerfacto user sees every
  warning nerfstudio and torch print, as without sp-plugins; warnings raised before our run starts
  (nerfstudio's imports, ``torch.jit.script``) still print once.
- ``SP_HOST_WARNINGS=1`` in the environment keeps every warning.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from typing import Iterator

from sp_plugins.patches.registry import Patch, python_patch

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


def _keep_all() -> bool:
    return os.environ.get("SP_HOST_WARNINGS", "") == "1"


@contextlib.contextmanager
def host_warnings_filtered() -> Iterator[bool]:
    """The filters for the block (yields False when ``SP_HOST_WARNINGS=1`` keeps them all). They are
    added to ``warnings.filters`` in place and exactly those entries are removed after, so the list
    is the same object with the entries it had (a filter someone else added meanwhile stays)."""
    if _keep_all():
        yield False
        return
    ours, before = [], list(warnings.filters)
    for category, message, module in HOST_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)
        if warnings.filters[0] not in before:  # (one already in force, e.g. process-wide, stays as it was)
            ours.append(warnings.filters[0])
    try:
        yield True
    finally:
        for entry in ours:
            for i, present in enumerate(warnings.filters):
                if present is entry:
                    del warnings.filters[i]
                    break
        warnings._filters_mutated()  # type: ignore[attr-defined]  (drop the per-module "once" caches)


def host_warnings_shown() -> bool:
    """Whether every filter is in ``warnings.filters`` now. A ``warnings.catch_warnings`` block that
    ends (pytest wraps every test in one) restores the list it saved, dropping filters a hold added
    inside it: a later scope then enters them again (registry ``Patch.shown``)."""
    present = {(f[1].pattern if f[1] is not None else None, f[2], f[3].pattern if f[3] is not None else None)
               for f in warnings.filters if f[0] == "ignore"}
    return all((message, category, module) in present for category, message, module in HOST_WARNINGS)


def _check(patch: Patch) -> None:
    patch.expect(isinstance(getattr(warnings, "filters", None), list), "warnings.filters a list",
                 f"warnings.filters = {type(getattr(warnings, 'filters', None)).__name__}")
    patch.expect(callable(getattr(warnings, "_filters_mutated", None)), "warnings._filters_mutated()",
                 "no warnings._filters_mutated")
    patch.expect(callable(getattr(warnings, "filterwarnings", None)), "warnings.filterwarnings()", "no warnings.filterwarnings")


PATCH = python_patch(
    "host_warnings", _check, host_warnings_filtered, (("warnings", "filters"), ("warnings", "_filters_mutated")),
    changes="warnings.filters: ignore the host's known, non-actionable messages (each by message and host module)",
    shown=lambda: _keep_all() or host_warnings_shown(),
    scope_text="under ns-* on a run of ours (its run config, model, data manager); process-wide in our sp-* commands")
