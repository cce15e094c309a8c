"""Checks of the files and settings a run is given, shared by the hosts' adapters and our commands.

Each raises :class:`~sp_plugins.adapter.errors.InputError` with one line naming the file or flag
and what was expected:

- :func:`check_checkpoint_file`: a checkpoint is a complete, undamaged PyTorch file (the zip's
  directory and every member's CRC: ``torch.load`` reads a file whose bytes were changed in place
  without noticing);
- :func:`check_known_settings`: a saved config (``config.yml``) was written by this version: no
  setting this version does not know, none missing that has no default;
- :func:`check_device`: the device a flag names exists on this machine;
- :func:`existing_outputs`: which of a command's result files an output folder already holds.

Imports no host.
"""

from __future__ import annotations

import dataclasses
import sys
import zipfile
from pathlib import Path
from typing import Any, Iterable, Iterator, List, Optional, Sequence, Tuple

from sp_plugins.adapter.hosts import Flags
from sp_plugins.adapter.errors import InputError, write_failure


def check_checkpoint_file(path: Path, flag: str = "") -> None:
    """``path`` is a readable PyTorch checkpoint (a zip whose members all pass their CRC check)."""
    where = f"{flag} {path}" if flag else str(path)
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{where}: checkpoint not found")
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
            names = archive.namelist()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        size = path.stat().st_size
        raise InputError(f"{where}: not a complete PyTorch checkpoint ({exc}; {size} bytes): the file is truncated or damaged "
                         "(an interrupted copy or save?) or is not a checkpoint; copy it again, or load another step") from None
    if bad is not None:
        raise InputError(f"{where}: damaged PyTorch checkpoint (member {bad} fails its CRC check): copy it again, or load "
                         "another step")
    if not any(name.endswith("data.pkl") for name in names):
        raise InputError(f"{where}: a zip file but not a PyTorch checkpoint (no data.pkl)")


def _versions() -> str:
    from importlib.metadata import PackageNotFoundError, version

    parts = []
    for dist in ("sp-plugins", "nerfstudio"):
        try:
            parts.append(f"{dist} {version(dist)}")
        except PackageNotFoundError:
            pass
    return ", ".join(parts)


def _walk(obj, prefix: str, seen: set) -> Iterator[Tuple[str, Any]]:  # the dataclass instances in obj
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        yield prefix, obj
        for f in dataclasses.fields(obj):
            if f.name in vars(obj):
                yield from _walk(vars(obj)[f.name], f"{prefix}.{f.name}", seen)
    elif isinstance(obj, dict):
        for key, value in obj.items():
            yield from _walk(value, f"{prefix}.{key}", seen)
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            yield from _walk(value, f"{prefix}[{i}]", seen)


def settings_problems(config: object, prefix: str) -> Tuple[List[str], List[str]]:
    """``(unknown, missing)`` dotted names in the dataclass tree ``config``: attributes its classes do
    not declare (a saved config from another version), and declared fields without a value or a
    default (a config saved before they existed, which nothing can fill in)."""
    unknown, missing = [], []
    for where, obj in _walk(config, prefix, set()):
        fields = {f.name: f for f in dataclasses.fields(obj)}
        for key in vars(obj):
            if key not in fields and not hasattr(type(obj), key):
                unknown.append(f"{where}.{key}")
        for name, f in fields.items():
            if name not in vars(obj) and not hasattr(type(obj), name):
                missing.append(f"{where}.{name}")
    return unknown, missing


def config_source(argv: Optional[Sequence[str]] = None) -> str:
    """The saved config a host command was given (``--load-config X`` in its arguments), for messages."""
    argv = list(sys.argv[1:] if argv is None else argv)
    for i, arg in enumerate(argv):
        if arg == "--load-config" and i + 1 < len(argv):
            return f"--load-config {argv[i + 1]}"
        if arg.startswith("--load-config="):
            return f"--load-config {arg.split('=', 1)[1]}"
    return "the run's config (config.yml)"


def check_known_settings(config: object, prefix: str, source: Optional[str] = None) -> None:
    """Refuse a saved config that another version wrote: settings this version does not know would
    be ignored silently, and settings it lacks that have no default cannot be filled in."""
    unknown, missing = settings_problems(config, prefix)
    if not unknown and not missing:
        return
    parts = []
    if unknown:
        parts.append(f"settings this version does not know ({', '.join(unknown[:4])}{', ...' if len(unknown) > 4 else ''})")
    if missing:
        parts.append(f"no value for {', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}")
    raise InputError(f"{source or config_source()}: written by another version of sp-plugins or its host: "
                     f"{' and '.join(parts)}; load it with the version that wrote it, or retrain (this is {_versions()})")


def check_device(device_type: str, count: int = 1, *, flags: Flags) -> None:
    """``count`` devices of ``device_type`` (cpu, cuda, mps) exist here; errors name the host's ``flags``."""
    import torch

    device, devices = flags.device, flags.devices
    if count < 1:  # before the host's launcher, which stops with a traceback (world_size cannot be 0)
        raise InputError(f"{devices} {count}: training needs at least one device; pass {devices} 1")
    if device_type == "cuda":
        available = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if available == 0:
            raise InputError(f"{device} cuda: CUDA is not available on this machine; pass {device} cpu")
        if count > available:
            raise InputError(f"{devices} {count}: this machine has {available} CUDA device(s)")
    elif device_type == "mps":
        if not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
            raise InputError(f"{device} mps: Apple's MPS is not available on this machine; pass {device} cpu")
    if device_type != "cuda" and count > 1:  # the hosts' launchers assert CUDA for more than one device
        raise InputError(f"{devices} {count}: training on more than one device needs {device} cuda; "
                         f"pass {devices} 1 (docs/guides/multi-process.md)")


def existing_outputs(out: Path, names: Iterable[str], flag: str) -> List[str]:
    """The ``names`` already in the folder ``out`` (a caller refuses them or replaces them);
    ``ValueError`` when ``out`` is a file (``flag`` names where it came from)."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"{flag} {out}: exists and is not a folder; choose another {flag}")
    return [name for name in names if (out / name).exists()]


def check_writable_dir(path: Path, flag: str) -> None:
    """Files can be created in folder ``path`` (or, when it does not exist yet, in the nearest folder
    above it that does): a transient probe file, so a read-only or full place is named before any
    work, and nothing is left behind."""
    import errno
    import os
    import tempfile

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: exists and is not a folder; choose another {flag}")
    probe_in = path.absolute()
    while not probe_in.exists():
        probe_in = probe_in.parent
    if not probe_in.is_dir():
        raise InputError(f"{flag} {path}: {probe_in} is a file, so the folder cannot be created; choose another {flag}")
    try:
        fd, name = tempfile.mkstemp(prefix=".sp-write-probe-", dir=probe_in)
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
            os.unlink(name)
    except OSError as exc:
        if exc.errno == errno.ENOENT:
            raise
        raise InputError(write_failure(exc, f"{flag} {path}")) from None
