"""A trained nerfstudio run, opened as our commands open one (``sp-export-mesh``, ``sp-compare``).

The ``config.yml`` is read with the restricted loader of :mod:`sp_plugins.adapter.safe_config` (also where
nerfstudio's ``eval_setup`` reads it again), so a file naming anything but what a training run writes is refused
in one line before anything is built; the checkpoint is read weights-only. Every failure is :class:`Refused`: one
line naming the file and what to do.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Callable, Optional, Tuple

from sp_plugins.adapter.checks import _versions, check_checkpoint_file
from sp_plugins.adapter.errors import describe_failure, first_line
from sp_plugins.adapter.safe_config import (
    ConfigRefused,
    load_run_config,
    reading_configs_safely,
    weights_only_checkpoints,
)


class Refused(Exception):
    """One line for the user; exit status 2."""


def answer(prog: str, command: Callable[[Any], int], args: Any) -> int:
    """``command(args)``, with :class:`Refused` printed as ``PROG: error: ...`` and exit status 2."""
    try:
        return command(args)
    except Refused as refused:
        print(f"{prog}: error: {refused}", file=sys.stderr)
        return 2


def model_sdf(model) -> Optional[Tuple[Callable, Any, Any]]:
    """``(sdf, aabb, device)`` of a nerfstudio model with an SDF field (``forward_geonetwork``, the callable nerfstudio
    meshes; ``aabb`` the scene box as a 2x3 float64 array), or None for a model without one."""
    if not hasattr(model.config, "sdf_field") or not hasattr(model.field, "forward_geonetwork"):
        return None
    device = next(model.parameters()).device

    def sdf(points):
        return model.field.forward_geonetwork(points.to(device))[:, 0]

    return sdf, model.scene_box.aabb.detach().cpu().double().numpy(), device


def versions() -> str:
    return _versions()


def load_saved_config(path: Path, flag: str = "--load-config"):
    """The ``TrainerConfig`` in ``path``, read with the restricted loader (nothing the file names is run), or
    :class:`Refused` naming the file and why (a tag no training run writes, a class this installation lacks, not YAML)."""
    if not path.is_file():
        raise Refused(f"{flag} {path}: config file not found; pass the config.yml that ns-train wrote")
    try:  # before nerfstudio is imported: a refused file is answered at once (a real one imports it by naming its classes)
        config = load_run_config(path, flag, versions=versions())
    except ConfigRefused as refused:
        raise Refused(str(refused)) from None
    from nerfstudio.engine.trainer import TrainerConfig

    if not isinstance(config, TrainerConfig):
        raise Refused(f"{flag} {path}: holds a {type(config).__name__}, not the TrainerConfig ns-train writes "
                      "(config.yml in the run folder)")
    return config


def _raised_in(exc: BaseException, function: str) -> bool:
    """``exc`` passed through a frame of ``function`` (by name)."""
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_name == function:
            return True
        tb = tb.tb_next
    return False


def setup_pipeline(path: Path, config, flag: str = "--load-config", test_mode: str = "inference") -> Tuple[Any, int]:
    """nerfstudio's ``eval_setup`` of the run whose ``config`` (read by :func:`load_saved_config`) is at ``path``:
    ``(pipeline, step)``, or :class:`Refused` in one line (a damaged or foreign checkpoint, an edited config)."""
    from nerfstudio.utils import eval_utils

    from sp_plugins.nerfstudio.components.trainer import checkpoint_to_load  # defers nerfstudio

    target = None
    try:
        config.load_dir, config.load_checkpoint = config.get_checkpoint_dir(), None
        target = checkpoint_to_load(config, dir_flag=f"{flag} {path}: its checkpoint folder")
        if target is not None:
            check_checkpoint_file(*target)
        # eval_setup reads the config.yml again itself: through the restricted loader too; its checkpoint weights-only
        with reading_configs_safely(eval_utils, f"{flag} {path}", versions()), weights_only_checkpoints():
            _, pipeline, _, step = eval_utils.eval_setup(path, test_mode=test_mode)
    except Exception as exc:  # noqa: BLE001  (a run folder the model cannot be set up from is answered in one line)
        message = describe_failure(exc)
        if message is None:
            detail = first_line(exc, 160)
            detail = detail if detail.startswith(type(exc).__name__) else f"{type(exc).__name__}: {detail}"
            if target is not None and _raised_in(exc, "eval_load_checkpoint"):
                message = (f"{target[0]}: not a checkpoint of this run ({detail}); it holds other contents than the "
                           "training run saved: copy it again, load another step, or retrain")
            else:
                message = (f"{flag} {path}: the model cannot be set up from this run ({detail}); its "
                           "config.yml was edited or written by another version: load it with the version that wrote it, "
                           "or retrain")
        raise Refused(message) from None
    return pipeline, step
