"""Checkpoints of a fitting task (``sp-fit --checkpoint-every N`` / ``--resume``).

A checkpoint is one file, ``checkpoint.pt`` in the output folder, written atomically (a temporary
file in the same folder, flushed to disk, then ``os.replace``): a run killed at any moment leaves
either the previous checkpoint or the new one, never a partial file. It holds the trainer's state
(:meth:`state_dict` of the task's trainer: field, optimiser and learning-rate schedule, the
preconditioner with its noise generator, the batch generator, step, loss history), the task's name
and the settings the trajectory depends on, which a resume compares with its own.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import torch

from sp_plugins.adapter.errors import load_failure_reason, refused_global

CHECKPOINT_NAME = "checkpoint.pt"
FORMAT = "sp-fit-checkpoint"
VERSION = 1
_TEMP_PREFIX = f".{CHECKPOINT_NAME}.tmp-"


def checkpoint_path(out: Union[str, Path]) -> Path:
    return Path(out) / CHECKPOINT_NAME


def save(path: Union[str, Path], payload: Mapping[str, Any]) -> Path:
    """Write ``payload`` to ``path`` atomically (temporary file + ``os.replace``)."""
    path = Path(path)
    tmp = path.with_name(f"{_TEMP_PREFIX}{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            torch.save(dict(payload, format=FORMAT, version=VERSION), f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def remove_stale(out: Union[str, Path], checkpoint_too: bool) -> None:
    """Delete temporary files a killed writer left in ``out`` (and the checkpoint itself)."""
    out = Path(out)
    for tmp in out.glob(f"{_TEMP_PREFIX}*"):
        tmp.unlink(missing_ok=True)
    if checkpoint_too:
        checkpoint_path(out).unlink(missing_ok=True)


def load(path: Union[str, Path], task: str) -> dict:
    """The checkpoint at ``path`` for ``task``; a ``ValueError`` in one line when there is none,
    it cannot be read, or it belongs to another task."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"--resume: no checkpoint in {path.parent} ({path.name} is missing); a run writes one "
                         "with --checkpoint-every N")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001  (any unpickling error: the file is not ours or is damaged)
        name = refused_global(exc)  # torch's first line would suggest loading it unsafely
        detail = (f"it holds a pickled {name}, which weights-only loading refuses; nothing in it was run" if name else
                  load_failure_reason(exc, 200))
        raise ValueError(f"--resume: {path} cannot be read as an sp-fit checkpoint ({detail[:200]})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"--resume: {path} is not an sp-fit checkpoint")
    if payload.get("version") != VERSION:
        raise ValueError(f"--resume: {path} was written by another version of sp-fit (format {payload.get('version')}, "
                         f"this one reads {VERSION}); start anew with --overwrite")
    if payload.get("task") != task:
        raise ValueError(f"--resume: {path} is a checkpoint of sp-fit {payload.get('task')}, not sp-fit {task}")
    return payload


def file_digest(path: Optional[Union[str, Path]]) -> Optional[str]:
    """SHA-256 of a file's bytes (None for None): a resume checks it was given the same data."""
    if path is None:
        return None
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def flatten(settings: Mapping[str, Any], prefix: str = "") -> dict:
    """``{"sp": {"alpha0": 1}}`` -> ``{"sp.alpha0": 1}``."""
    flat = {}
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + "."))
        else:
            flat[name] = list(value) if isinstance(value, tuple) else value
    return flat


def differences(saved: Mapping[str, Any], current: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """``(name, current value, saved value)`` for each setting that differs, in ``current``'s order."""
    a, b = flatten(current), flatten(saved)
    missing = object()
    out = [(k, a[k], b.get(k, missing)) for k in a if b.get(k, missing) != a[k]]
    out += [(k, missing, b[k]) for k in b if k not in a]
    return [(k, None if v is missing else v, None if w is missing else w) for k, v, w in out]
