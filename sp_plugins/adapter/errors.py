"""Bad input under a host's commands (``ns-train``...): one line naming the problem, not a stack trace.

nerfstudio's commands have no error handler, so an exception raised while the trainer sets up
prints a deep traceback. Our own input checks raise :class:`InputError` (a ``ValueError``); an
exception hook prints an uncaught ``InputError`` as ``<command>: error: ...`` and exits with
status 2. Every other exception keeps Python's (or the host's) usual report. The hook goes in
when one of our methods is built or in our own commands, never at import: a process that trains
only other methods keeps its hook.
"""

from __future__ import annotations

import sys
from pathlib import Path


class InputError(ValueError):
    """Input a user can fix (a missing folder, a wrong layout, a flag that does not fit)."""


def _one_line_input_errors(previous):
    def hook(kind, value, traceback):
        if issubclass(kind, InputError):
            print(f"{Path(sys.argv[0]).name}: error: {value}", file=sys.stderr)
            raise SystemExit(2)
        previous(kind, value, traceback)

    hook.sp_plugins_input_errors = True  # type: ignore[attr-defined]
    return hook


def install_input_error_hook() -> None:
    """Idempotent: wraps whatever hook is installed (Python's, rich's...)."""
    if not getattr(sys.excepthook, "sp_plugins_input_errors", False):
        sys.excepthook = _one_line_input_errors(sys.excepthook)
