"""Take about 2 s off the start of every ``ns-*`` command.

Targets nerfstudio 1.1.5 (see ``TESTED_NERFSTUDIO_VERSIONS``). There, importing
``nerfstudio.configs.method_configs`` (which every ``ns-train`` / ``ns-eval`` / ``ns-export`` /
``ns-render`` does) builds one ``ExternalMethodDummyTrainerConfig`` per installable external method
(26 of them), and its ``__post_init__`` calls ``inspect.stack()`` only to ask whether its caller's
caller is ``get_external_methods``. ``inspect.stack()`` reads the source file of every frame and
scans ``sys.modules`` (over 4000 modules once torch and nerfstudio are loaded): about 2 s per
command on our 2-core CPU, 26 calls at 0.08 s (``python -m bench.ns_startup``).

The patch asks the same question of the frame's code object (``sys._getframe``), which costs
microseconds, and hands every other case (the CLI building the dummy, which offers to install the
method) to the original method unchanged.

Where it goes in (registry entry ``nerfstudio_external_methods``): only in our own command,
``sp-train``, for its whole process (``registry.install_for_process``), before it imports
nerfstudio's method list. Installing sp-plugins must change nothing for ``ns-*`` commands that train methods not ours,
and nerfstudio imports every plugin's method configs in all of them, so discovery does not install
it: plain ``ns-train`` / ``ns-eval`` keep nerfstudio's start-up time.
"""

from __future__ import annotations

import importlib.metadata
import contextlib
import inspect
import logging
import sys
from typing import Iterator

from sp_plugins.patches.registry import Patch, nerfstudio_patch

logger = logging.getLogger(__name__)

TESTED_NERFSTUDIO_VERSIONS: tuple[str, ...] = ("1.1.5",)
HOST_CHECK = 'inspect.stack()[2].function == "get_external_methods"'
CALLER = "get_external_methods"


def _host_class():
    from nerfstudio.configs.external_methods import ExternalMethodDummyTrainerConfig

    return ExternalMethodDummyTrainerConfig


def host_post_init_is_as_expected(cls=None) -> bool:
    """True when the host's ``__post_init__`` still makes the ``inspect.stack()`` check this patch
    replaces (checked on the source; False when it cannot be read)."""
    cls = cls or _host_class()
    original = getattr(cls.__post_init__, "__sp_original__", cls.__post_init__)
    try:
        return HOST_CHECK in inspect.getsource(original)
    except (OSError, TypeError):
        return False


def install_fast_external_methods() -> bool:
    """Replace ``ExternalMethodDummyTrainerConfig.__post_init__`` with the frame-based check (what
    the registry's scope does; ``bench.speed.ns_startup`` measures it). Idempotent. Returns False
    (and changes nothing) when the host's method no longer makes the check this patch is written
    for."""
    try:
        cls = _host_class()
    except ImportError:
        return False
    if getattr(cls.__post_init__, "__sp_original__", None) is not None:
        return True
    if not host_post_init_is_as_expected(cls):
        version = importlib.metadata.version("nerfstudio")
        logger.debug("nerfstudio %s: external-method startup patch not applied (written for %s)", version, TESTED_NERFSTUDIO_VERSIONS)
        return False
    original = cls.__post_init__

    def __post_init__(self) -> None:
        # frame 0: this method, 1: the dataclass __init__, 2: whoever built the dummy
        if sys._getframe(2).f_code.co_name == CALLER:
            return
        original(self)

    __post_init__.__sp_original__ = original  # type: ignore[attr-defined]
    __post_init__.__doc__ = original.__doc__
    cls.__post_init__ = __post_init__
    return True


@contextlib.contextmanager
def fast_external_methods() -> Iterator[bool]:
    """The frame-based check for the block; nerfstudio's ``__post_init__`` again after it."""
    cls = _host_class()
    before = cls.__dict__.get("__post_init__")
    active = install_fast_external_methods()
    try:
        yield active
    finally:
        if before is None:
            if "__post_init__" in cls.__dict__:
                delattr(cls, "__post_init__")
        else:
            cls.__post_init__ = before


def _check(patch: Patch) -> None:
    try:
        cls = _host_class()
    except ImportError as exc:
        patch.fail("nerfstudio.configs.external_methods.ExternalMethodDummyTrainerConfig", f"ImportError: {exc}")
    patch.expect(callable(getattr(cls, "__post_init__", None)), "ExternalMethodDummyTrainerConfig.__post_init__", "none")
    patch.expect(host_post_init_is_as_expected(cls), f"ExternalMethodDummyTrainerConfig.__post_init__ checking {HOST_CHECK}",
                 "a __post_init__ without that check")


PATCH = nerfstudio_patch(
    "nerfstudio_external_methods", TESTED_NERFSTUDIO_VERSIONS, _check, fast_external_methods,
    (("nerfstudio.configs.external_methods", "ExternalMethodDummyTrainerConfig"),), owned_commands=("sp-train",),
    changes="ExternalMethodDummyTrainerConfig.__post_init__: asks sys._getframe instead of inspect.stack() (2 s off start-up)",
    scope_text="process-wide in sp-train only (before it imports nerfstudio's method list)")
