"""Bad input under a host's commands (``ns-train``...): one line naming the problem, not a stack trace.

nerfstudio's commands have no error handler, so an exception raised while the trainer sets up
prints a deep traceback. Our own input checks raise :class:`InputError` (a ``ValueError``); an
exception hook (registry entry ``input_error_hook``, :mod:`sp_plugins.patches.input_error_hook`)
prints an uncaught ``InputError`` as ``<command>: error: ...`` and exits with status 2. The same hook recognizes a few failures the host's own code hits on bad files, from
where they were raised (:func:`describe_failure`): a checkpoint that ``torch.load`` cannot read
(truncated, damaged, not a checkpoint), a checkpoint that ``torch.save`` could not write (full
disk; the partial file is removed), and an ``OSError`` writing a file (read-only folder, full
disk, no permission). Every other exception keeps Python's (or the host's) usual report. The hook
goes in when one of our methods is built or in our own commands, never at import: a process that
trains only other methods keeps its hook.
"""

from __future__ import annotations

import errno
import os
import re
from types import TracebackType
from typing import Optional

from sp_plugins.patches import registry


class InputError(ValueError):
    """Input a user can fix (a missing folder, a wrong layout, a flag that does not fit).

    Raised under any command (a host's ``ns-eval`` included), it reaches the top of the process as
    one line: the error itself holds the one-line hook while it exists
    (:func:`sp_plugins.patches.registry.hold`, entry ``input_error_hook``), so nothing else in the
    process (building a model, loading a run) installs a hook."""

    def __init__(self, *args: object) -> None:
        super().__init__(*args)
        registry.hold("input_error_hook", self)


WRITE_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EFBIG}
"""``OSError`` numbers that mean "this place cannot take the file": permissions, a read-only file
system, a full disk or quota, a file-size limit."""


def first_line(exc: BaseException, limit: int = 200) -> str:
    """The first line of ``exc``'s message (its type's name when it has none), at most ``limit`` characters."""
    text = str(exc).strip()
    if isinstance(exc, KeyError) or not text:
        text = f"{type(exc).__name__}{': ' + text if text else ''}"
    line = text.splitlines()[0]
    return line if len(line) <= limit else line[: limit - 3] + "..."


def write_failure(exc: OSError, what: Optional[str] = None, name: Optional[str] = None) -> str:
    """One line for an ``OSError`` that stopped a write (``what``: the place to name, default the
    error's file name; ``name``: the file that was being written there)."""
    where = what or exc.filename or "the output"
    reason = f"{name}: {exc.strerror or first_line(exc)}" if name else (exc.strerror or first_line(exc))
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        hint = "the disk is full (or a quota or file-size limit is reached): free space or write elsewhere"
    elif exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        hint = "the folder is read-only or not yours: choose a writable output folder"
    else:
        hint = "choose another output folder"
    return f"{where}: cannot write ({reason}); {hint}"


def _frames(tb: Optional[TracebackType]):
    while tb is not None:
        yield tb.tb_frame
        tb = tb.tb_next


def _torch_frame(tb: Optional[TracebackType], name: str):
    """The frame of ``torch.serialization.<name>`` in traceback ``tb`` (the outermost), or None."""
    for frame in _frames(tb):
        code = frame.f_code
        if code.co_name == name and code.co_filename.replace(os.sep, "/").endswith("torch/serialization.py"):
            return frame
    return None


def _path_of(handle) -> Optional[str]:
    if isinstance(handle, (str, os.PathLike)):
        return os.fspath(handle)
    name = getattr(handle, "name", None)
    return name if isinstance(name, str) else None


def refused_global(exc: BaseException) -> Optional[str]:
    """The global (``posix.system``, ``builtins.print``...) a weights-only ``torch.load`` refused to
    unpickle, from its error message; None for any other failure."""
    found = re.search(r"[Uu]nsupported (?:global: )?GLOBAL ([\w.]+)", str(exc))
    return found.group(1) if found else None


_TORCH_BOILERPLATE = ("Weights only load failed", "Please file an issue", "Check the documentation", "(1)", "(2)",
                      "In PyTorch 2.6", "Re-running")


def load_failure_reason(exc: BaseException, limit: int = 120) -> str:
    """What ``torch.load`` said went wrong, in one line: for a weights-only refusal, torch's own
    reason (``Unsupported operand 153``) rather than its first line, which suggests loading the
    file with ``weights_only=False``."""
    text = str(exc)
    if "Weights only load failed" not in text:
        return first_line(exc, limit)
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    reasons = [line.split("WeightsUnpickler error:", 1)[-1].strip() for line in lines
               if not line.startswith(_TORCH_BOILERPLATE)]
    reason = "; ".join(r for r in reasons if r) or "refused"
    reason = f"weights-only unpickling: {reason}"
    return reason if len(reason) <= limit else reason[: limit - 3] + "..."


def describe_failure(exc: BaseException, tb: Optional[TracebackType] = None) -> Optional[str]:
    """One line for a failure a user can fix that host code raised on a bad file, or None.

    - raised inside ``torch.load``: the checkpoint (named) is truncated, damaged or not a checkpoint;
    - raised inside ``torch.save``: the checkpoint could not be written (its partial file is
      deleted, so a later resume does not pick it up as the latest);
    - an ``OSError`` of :data:`WRITE_ERRNOS` with a file name: that file could not be written;
    - an error of ``wandb`` (``--vis wandb``, the host's default for mipnerf and vanilla-nerf, without
      an account): how to log in, or the front ends that need none.
    """
    tb = tb if tb is not None else exc.__traceback__
    if isinstance(exc, InputError):
        return str(exc)
    if type(exc).__module__.split(".")[0] == "wandb":  # --vis wandb without an account (the host's mipnerf default)
        return (f"--vis wandb: wandb could not start ({type(exc).__name__}: {first_line(exc, 120)}); it needs an account: "
                "log in with `wandb login` (or set WANDB_MODE=offline), or pass --vis viewer (nerfstudio's web viewer) "
                "or --vis tensorboard")
    load = _torch_frame(tb, "load")
    if load is not None:
        path: Optional[str] = _path_of(load.f_locals.get("f")) or "the checkpoint"
        if isinstance(exc, OSError) and exc.errno == errno.ENOENT:
            return f"{path}: checkpoint not found"
        refused = refused_global(exc)
        if refused:
            return (f"{path}: holds a pickled {refused}, which torch's weights-only loading refuses (nothing in the file was "
                    "run); it was written by another version (e.g. nerfstudio's schedulers stored numpy learning rates) or "
                    "not by a training run: retrain with this version, and load checkpoints only from sources you trust")
        return (f"{path}: cannot be read as a PyTorch checkpoint ({load_failure_reason(exc)}); the file is truncated or "
                "damaged (an interrupted copy or save?) or is not a checkpoint: copy it again, or load another step")
    save = _torch_frame(tb, "save")
    if save is not None:
        path = _path_of(save.f_locals.get("f"))
        removed = ""
        if path is not None and os.path.isfile(path):
            try:
                os.unlink(path)  # a partial checkpoint would be taken for the latest one by a resume
                removed = " (the partial file was removed)"
            except OSError:
                pass
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else first_line(exc, 120)
        return (f"{path or 'the checkpoint'}: writing the checkpoint failed ({reason}); the disk is probably full or the "
                f"folder read-only{removed}: free space or choose another output folder")
    if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS and exc.filename:
        return write_failure(exc)
    return None


NETWORK_MODULES = ("requests", "urllib3", "httpx", "aiohttp", "huggingface_hub")
"""Download libraries whose errors (``OSError`` subclasses) mean the network was not reached."""


def is_network_error(exc: BaseException) -> bool:
    """``exc`` says a download could not reach the network (``urllib``, ``socket``, ``requests``...)."""
    import socket
    import urllib.error

    if isinstance(exc, (urllib.error.URLError, socket.gaierror, socket.herror, ConnectionError, TimeoutError)):
        return True
    return isinstance(exc, OSError) and type(exc).__module__.split(".")[0] in NETWORK_MODULES


def provider(cls: type) -> str:
    """Who ships class ``cls``: ``the plugin <distribution> <version>`` (or its top-level module
    when no installed distribution declares it), or ``nerfstudio`` for the host's own classes."""
    from importlib.metadata import packages_distributions, version

    top = cls.__module__.split(".")[0]
    if top == "nerfstudio":
        return "nerfstudio"
    dists = packages_distributions().get(top, [])
    if not dists:
        return f"the plugin {top}"
    try:
        found = version(dists[0])  # None for metadata without a Version on Python 3.11
    except Exception:  # noqa: BLE001  (metadata without a version, where version() raises)
        found = None
    return f"the plugin {dists[0]} {found}" if found else f"the plugin {dists[0]}"


def build_failure(exc: BaseException, cls: type, step: str) -> Optional[str]:
    """One line for a host model that failed while ``step`` ran for a reason of its environment a
    user can fix (no network for a download, a file it needs), naming who ships ``cls``, the step
    and the cause; None for any other exception (a bug keeps its traceback for the plugin's author)."""
    if not isinstance(exc, OSError):
        return None
    cause = f"{type(exc).__name__}: {first_line(exc, 160)}"
    if is_network_error(exc):
        hint = ("it downloads files while the model is built and could not reach the network: connect to the network, "
                "or fetch the files it needs beforehand (see its documentation)")
    else:
        hint = "a file or folder it needs is missing or unreadable: see its documentation for what it needs"
    return f"{cls.__name__} of {provider(cls)} failed while {step} ({cause}); {hint}"
