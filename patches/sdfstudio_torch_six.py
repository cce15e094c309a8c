"""``torch._six`` is gone from torch >= 2.0; sdfstudio still imports it (registry entry
``sdfstudio_torch_six``).

Targets sdfstudio commit 370902a: ``nerfstudio/data/utils/nerfstudio_collate.py`` does
``from torch._six import string_classes`` (the only name it uses). When torch has no ``_six``,
sdfstudio's modules (only) are given, through the import hook
(:mod:`sp_plugins.patches.sdfstudio_import_hook`), a module of that name holding
``string_classes = (str,)`` (its value in torch 1.x on Python 3). Nothing is put in
``sys.modules``: for any other module ``import torch._six`` fails as torch made it. A torch that
still ships ``_six`` is left alone.
"""

from __future__ import annotations

import contextlib
import importlib.util
import types
from typing import Iterator

from sp_plugins.patches.registry import Patch
from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT, expect_source, patching, sdfstudio_patch

__all__ = ["HOST_COMMIT", "PATCH", "STAND_IN", "torch_six_for_sdfstudio"]

STAND_IN = types.ModuleType("torch._six", "Stand-in given to sdfstudio's modules by sp_plugins.patches.sdfstudio_torch_six.")
STAND_IN.string_classes = (str,)  # type: ignore[attr-defined]


def torch_has_six() -> bool:
    import torch  # noqa: F401  (so that find_spec can look inside it)

    return importlib.util.find_spec("torch._six") is not None


@contextlib.contextmanager
def torch_six_for_sdfstudio() -> Iterator[bool]:
    """sdfstudio modules executed within this block import :data:`STAND_IN` as ``torch._six``."""
    if torch_has_six():
        yield False
        return
    with patching(imports={"torch._six": lambda: STAND_IN}):
        yield True


def _check(patch: Patch) -> None:
    expect_source(patch, "nerfstudio/data/utils/nerfstudio_collate.py", "from torch._six import string_classes")


PATCH = sdfstudio_patch(
    "sdfstudio_torch_six", _check, torch_six_for_sdfstudio, "nerfstudio/data/utils/nerfstudio_collate.py",
    changes="`torch._six` as imported by sdfstudio's modules only (torch >= 2 has none): string_classes = (str,)",
    scope_text="sdfstudio's modules executed in the block; process-wide (those modules only) in sp-sdfstudio-* / the hook")
