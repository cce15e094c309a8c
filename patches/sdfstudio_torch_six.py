"""``torch._six`` is gone from torch >= 2.0; sdfstudio still imports it.

Targets sdfstudio commit 370902a: ``nerfstudio/data/utils/nerfstudio_collate.py`` does
``from torch._six import string_classes`` (the only name it uses). When torch has no ``_six``,
a module of that name holding ``string_classes = (str,)`` (its value in torch 1.x on Python 3) is
registered; a torch that still ships ``_six`` is left alone.
"""

from __future__ import annotations

import importlib.util
import sys
import types

from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT

__all__ = ["HOST_COMMIT", "install"]


def install() -> None:
    if "torch._six" in sys.modules:
        return
    import torch  # noqa: F401  (so that find_spec can look inside it)

    if importlib.util.find_spec("torch._six") is not None:
        return
    six = types.ModuleType("torch._six", "Stand-in registered by sp_plugins.patches.sdfstudio_torch_six.")
    six.string_classes = (str,)
    sys.modules["torch._six"] = six
