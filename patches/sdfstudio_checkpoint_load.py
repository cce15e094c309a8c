"""sdfstudio's checkpoint loads on torch >= 2.6: numpy learning rates allowed, nothing else.

Targets sdfstudio commit 370902a. Its two checkpoint loads, ``Trainer._load_checkpoint`` (``ns-train
--trainer.load-dir``) and ``eval_utils.eval_load_checkpoint`` (``eval_setup``: ``ns-eval``,
``ns-extract-mesh``, ``ns-render``, our ``sp-sdfstudio-extract-mesh``), call
``torch.load(path, map_location="cpu")``. torch >= 2.6 loads weights-only by default, and
sdfstudio's ``LambdaLR`` schedulers compute their factor with numpy: ``NeuSScheduler`` and
``MultiStepWarmupScheduler`` once past their warm-up (5000 steps for neus and most methods, 500 for
some), ``ExponentialDecaySchedule`` (``SchedulerConfig``, e.g. the camera optimizer's) from the first
step. From then on the optimizers' ``lr`` and the schedulers' ``_last_lr`` are numpy float64 in every
checkpoint, weights-only unpickling refuses them (``Unsupported global: numpy.core.multiarray.scalar``),
and the run can be neither resumed nor evaluated nor meshed: our methods' runs and sdfstudio's own.

While those two functions run, ``torch.load`` also accepts numpy's scalar and dtype
reconstructors (``torch.serialization.safe_globals``), for plain numbers only (bool, integer,
float and complex dtypes; not object, string, bytes, void or time dtypes): still weights-only (no
code runs from a checkpoint), and only there; every other ``torch.load`` in the process keeps
torch's default.
(The nerfstudio adapter meets the same host bug by keeping our methods' learning rates Python
floats, :mod:`sp_plugins.nerfstudio.components.schedulers`, because a nerfstudio checkpoint may be loaded
where the plugin is not imported; sdfstudio at 370902a runs on torch 2.x only with these patches,
and this way checkpoints already written, and sdfstudio's own methods', load too.) A torch
without ``safe_globals`` (< 2.5) loads without weights-only by default: nothing to do there.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
from typing import Callable, Iterator, List

import torch

from sp_plugins.patches.registry import Patch
from sp_plugins.patches.sdfstudio_import_hook import (
    HOST_COMMIT, expect_attribute, expect_source, patching, sdfstudio_patch,
)

__all__ = ["HOST_COMMIT", "PATCH", "numpy_scalar_globals"]

_MARK = "_sp_numpy_scalars_allowed"


def _plain_number_dtype(cls) -> bool:
    """A ``numpy.dtypes`` class of a plain number (``Float64DType``...): bool, integer, float, complex;
    not timedelta64 (numpy counts it an integer), object, string, bytes or void."""
    import numpy as np

    kind = getattr(cls, "type", None)
    return (isinstance(cls, type) and isinstance(kind, type)
            and issubclass(kind, (np.bool_, np.integer, np.floating, np.complexfloating))
            and not issubclass(kind, np.timedelta64))


def numpy_scalar_globals() -> List[object]:
    """What a pickled numpy number needs: ``numpy.dtype``, the classes of the plain number dtypes
    (``numpy.dtypes``, numpy >= 1.25: ``Float64DType`` for a learning rate) and ``multiarray.scalar``
    (under ``numpy.core`` in numpy 1.x, ``numpy._core`` in 2.x)."""
    import numpy as np

    found: List[object] = [np.dtype]
    dtypes = getattr(np, "dtypes", None)
    if dtypes is not None:
        found += [cls for name, cls in sorted(vars(dtypes).items()) if name.endswith("DType") and _plain_number_dtype(cls)]
    for module in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            scalar = importlib.import_module(module).scalar
        except (ImportError, AttributeError):
            continue
        found.append(scalar)
        break  # numpy 2 keeps numpy.core as a deprecated alias of numpy._core
    return found


def allow_numpy_scalars(fn: Callable) -> Callable:
    """``fn`` with numpy scalars allowed in its weights-only ``torch.load`` calls."""
    if getattr(fn, _MARK, False) or not hasattr(torch.serialization, "safe_globals"):
        return fn

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with torch.serialization.safe_globals(numpy_scalar_globals()):
            return fn(*args, **kwargs)

    setattr(wrapper, _MARK, True)
    return wrapper


def _patch_trainer(module, rebind) -> None:
    cls = expect_attribute(PATCH, module, "Trainer")
    rebind(cls, "_load_checkpoint", allow_numpy_scalars(expect_attribute(PATCH, cls, "_load_checkpoint", "torch.load(")))


def _patch_eval_utils(module, rebind) -> None:  # eval_setup calls it through the module's globals
    rebind(module, "eval_load_checkpoint", allow_numpy_scalars(expect_attribute(PATCH, module, "eval_load_checkpoint", "torch.load(")))


@contextlib.contextmanager
def numpy_scalars_in_sdfstudio_loads() -> Iterator[None]:
    with patching(after={"nerfstudio.engine.trainer": _patch_trainer, "nerfstudio.utils.eval_utils": _patch_eval_utils}):
        yield


def _check(patch: Patch) -> None:
    expect_source(patch, "nerfstudio/engine/trainer.py", "torch.load(")
    expect_source(patch, "nerfstudio/utils/eval_utils.py", "torch.load(")
    patch.expect(callable(getattr(torch, "load", None)), "torch.load", f"torch.load = {getattr(torch, 'load', None)!r}")


PATCH = sdfstudio_patch(
    "sdfstudio_checkpoint_load", _check, numpy_scalars_in_sdfstudio_loads, "nerfstudio/engine/trainer.py",
    "nerfstudio/utils/eval_utils.py", guarded=(("torch", "load"),),
    changes="Trainer._load_checkpoint and eval_utils.eval_load_checkpoint: weights-only torch.load also accepts numpy's plain scalars",
    scope_text="those two sdfstudio functions' calls (safe_globals per call); process-wide (those modules) in sp-sdfstudio-* / the hook")
