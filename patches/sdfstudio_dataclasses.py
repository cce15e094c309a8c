"""Python 3.11 rejects sdfstudio's mutable dataclass defaults; sdfstudio's modules get a tolerant
``dataclass`` of their own (registry entry ``sdfstudio_dataclasses``).

Targets sdfstudio commit 370902a: about 20 config fields are written ``x: Cfg = Cfg()`` (e.g.
``SurfaceModelConfig.sdf_field``, ``Config.trainer``). Since Python 3.11 ``dataclass`` raises
``ValueError: mutable default ... use default_factory`` for any unhashable default, so those
modules cannot even be imported.

An sdfstudio module that imports ``dataclasses`` (``import dataclasses`` or ``from dataclasses
import dataclass, field``) is given :data:`TOLERANT`, a module of its own through the import hook
(:mod:`sp_plugins.patches.sdfstudio_import_hook`): everything of the real ``dataclasses`` except
``dataclass``, which turns exactly the defaults that Python 3.11 would reject into
``field(default_factory=...)`` returning a deep copy of the written default, which is what the
author meant (each config gets its own copy; tyro shows the same default). ``dataclasses.dataclass``
itself is never swapped: every other module, a third-party one first imported by sdfstudio
included, gets Python's.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import types
from typing import Iterator

from sp_plugins.patches.registry import Patch
from sp_plugins.patches.sdfstudio_import_hook import (
    HOST_COMMIT, expect_source, patching, sdfstudio_patch,
)

__all__ = ["HOST_COMMIT", "PATCH", "TOLERANT", "rejected_by_python", "tolerant_dataclasses"]


def rejected_by_python(value) -> bool:
    """The test Python 3.11's ``dataclass`` applies to a default (unhashable -> rejected)."""
    return not isinstance(value, dataclasses.Field) and type(value).__hash__ is None


def defaults_to_factories(cls: type) -> type:
    """Replace each rejected class-level default of ``cls`` by a deep-copying default_factory."""
    for name in cls.__dict__.get("__annotations__", {}):
        value = cls.__dict__.get(name, dataclasses.MISSING)
        if value is not dataclasses.MISSING and rejected_by_python(value):
            setattr(cls, name, dataclasses.field(default_factory=functools.partial(copy.deepcopy, value)))
    return cls


def _tolerant_dataclass(cls=None, /, **kwargs):
    def wrap(c):
        return dataclasses.dataclass(defaults_to_factories(c), **kwargs)

    return wrap if cls is None else wrap(cls)


class _TolerantDataclasses(types.ModuleType):
    """``dataclasses`` as sdfstudio's modules see it: the real module's names, a tolerant ``dataclass``."""

    dataclass = staticmethod(_tolerant_dataclass)

    def __getattr__(self, name: str):
        return getattr(dataclasses, name)


TOLERANT = _TolerantDataclasses("dataclasses", "dataclasses for sdfstudio's modules (sp_plugins.patches.sdfstudio_dataclasses)")


@contextlib.contextmanager
def tolerant_dataclasses() -> Iterator[None]:
    """sdfstudio modules executed within this block get :data:`TOLERANT` for ``dataclasses``."""
    with patching(imports={"dataclasses": lambda: TOLERANT}):
        yield


def _check(patch: Patch) -> None:
    expect_source(patch, "nerfstudio/configs/base_config.py", "from dataclasses import dataclass")
    real = getattr(dataclasses, "dataclass", None)
    patch.expect(callable(real) and getattr(real, "__module__", "") == "dataclasses", "Python's dataclasses.dataclass",
                 f"dataclasses.dataclass = {real!r}")


PATCH = sdfstudio_patch(
    "sdfstudio_dataclasses", _check, tolerant_dataclasses, "nerfstudio/configs/base_config.py", guarded=(("dataclasses", "dataclass"),),
    changes="`dataclasses` as imported by sdfstudio's modules only: a dataclass that turns mutable defaults into default_factory",
    scope_text="sdfstudio's modules executed in the block; process-wide (those modules only) in sp-sdfstudio-* / the hook")
