"""One line (``<command>: error: ...``, exit status 2) instead of a traceback for the failures our
checks describe (:func:`sp_plugins.adapter.errors.describe_failure`: bad input, a damaged
checkpoint, a full disk).

Python calls ``sys.excepthook`` for an exception that reaches the top of the process. The patch
wraps whatever hook is installed (Python's, rich's ...): a described failure prints its line and
exits 2, anything else goes to the previous hook.

Scope: our console commands own their process and keep it until the process ends. Under
nerfstudio's ``ns-*`` commands working on a run of ours it is held
(:func:`sp_plugins.patches.registry.hold`) by that run's objects (``ns-train``'s checked run config;
our model and data manager under ``ns-eval`` / ``ns-render`` / ``ns-export`` / ``ns-viewer``), so a
failure while they exist (a bad input, a damaged checkpoint) reaches the top as one line (the
traceback keeps them alive). In a Python session, a notebook or a test, building our model installs
nothing; there each ``InputError`` of ours holds the hook while it exists. Once the
holders are gone ``sys.excepthook`` is again the hook it was. A hook someone installed over ours
meanwhile is left in place; ours then only passes through.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Iterator

from sp_plugins.adapter.errors import describe_failure
from sp_plugins.patches.registry import Patch, python_patch

__all__ = ["PATCH", "input_errors_as_one_line"]


def _one_line_hook(previous):
    def hook(kind, value, traceback):
        if hook.sp_plugins_input_errors and isinstance(value, Exception):
            message = describe_failure(value, traceback)
            if message is not None:
                print(f"{Path(sys.argv[0]).name}: error: {message}", file=sys.stderr)
                sys.stderr.flush()
                raise SystemExit(2)
        previous(kind, value, traceback)

    hook.sp_plugins_input_errors = True  # type: ignore[attr-defined]
    return hook


@contextlib.contextmanager
def input_errors_as_one_line() -> Iterator[None]:
    previous = sys.excepthook
    if getattr(previous, "sp_plugins_input_errors", False):  # already in force (an outer scope)
        yield
        return
    hook = _one_line_hook(previous)
    sys.excepthook = hook
    try:
        yield
    finally:
        if sys.excepthook is hook:
            sys.excepthook = previous
        else:  # someone wrapped it: ours stays in their chain, passing everything through
            hook.sp_plugins_input_errors = False  # type: ignore[attr-defined]


def _check(patch: Patch) -> None:
    hook = getattr(sys, "excepthook", None)
    patch.expect(callable(hook), "a callable sys.excepthook", f"sys.excepthook = {type(hook).__name__}")
    patch.expect(callable(getattr(sys, "__excepthook__", None)), "sys.__excepthook__", "none")


PATCH = python_patch(
    "input_error_hook", _check, input_errors_as_one_line, (("sys", "excepthook"), ("sys", "__excepthook__")),
    changes="sys.excepthook: wraps the hook in force; a failure our checks describe prints one line and exits 2",
    shown=lambda: getattr(sys.excepthook, "sp_plugins_input_errors", False),
    scope_text="under ns-* on a run of ours (its run config, model, data manager), or while an InputError of ours exists; process-wide in our sp-* commands")
