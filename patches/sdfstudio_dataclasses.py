"""Python 3.11 rejects sdfstudio's mutable dataclass defaults; run its modules with a tolerant
``dataclasses.dataclass``.

Targets sdfstudio commit 370902a: about 20 config fields are written ``x: Cfg = Cfg()`` (e.g.
``SurfaceModelConfig.sdf_field``, ``Config.trainer``). Since Python 3.11 ``dataclass`` raises
``ValueError: mutable default ... use default_factory`` for any unhashable default, so those
modules cannot even be imported.

While an sdfstudio module executes (see :mod:`sp_plugins.patches.sdfstudio_import_hook`),
``dataclasses.dataclass`` turns exactly the defaults that Python 3.11 would reject into
``field(default_factory=...)`` returning a deep copy of the written default, which is what the
author meant (each config gets its own copy; tyro shows the same default). Every other class is
built by the real ``dataclass`` unchanged; outside sdfstudio's modules nothing is swapped.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
from typing import Iterator

from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT, around_exec

__all__ = ["HOST_COMMIT", "install", "rejected_by_python", "tolerant_dataclasses"]

_real_dataclass = dataclasses.dataclass


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
        return _real_dataclass(defaults_to_factories(c), **kwargs)

    return wrap if cls is None else wrap(cls)


@contextlib.contextmanager
def tolerant_dataclasses() -> Iterator[None]:
    """Within this block ``dataclasses.dataclass`` accepts mutable defaults (see module doc)."""
    previous = dataclasses.dataclass
    dataclasses.dataclass = _tolerant_dataclass
    try:
        yield
    finally:
        dataclasses.dataclass = previous


def install() -> None:
    around_exec(tolerant_dataclasses)
