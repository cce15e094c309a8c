"""Lookups over a host's method tables (``sp_plugins.<host>.table``): dicts keyed by a host class's
path (``module.QualName``), an entry applying to that class and its subclasses."""

from __future__ import annotations

from typing import Dict, Mapping, Optional, Tuple, TypeVar

from sp_plugins.adapter.variants import class_path

V = TypeVar("V")


def lookup(table: Mapping[str, V], cls: Optional[type]) -> Optional[Tuple[str, V]]:
    """``(path, value)`` of the most derived class in ``cls``'s MRO that ``table`` names (None: none)."""
    for base in cls.__mro__ if cls is not None else ():
        path = class_path(base)
        if path in table:
            return path, table[path]
    return None


def merged(table: Mapping[str, Dict[str, V]], cls: type) -> Dict[str, V]:
    """The entries of every class in ``cls``'s MRO, merged; where two name the same key, the most
    derived class wins, as in :func:`lookup`."""
    out: Dict[str, V] = {}
    for base in reversed(cls.__mro__):
        out.update(table.get(class_path(base), {}))
    return out


def read_point(read_points: Mapping[str, str], cls: Optional[type]) -> str:
    """The ``Frustums`` accessor a field of class ``cls`` queries at: ``read_points``' entry (a host table's
    ``READ_POINTS``) for it or its nearest base, else ``get_positions``, the default."""
    found = lookup(read_points, cls)
    return found[1] if found else "get_positions"
