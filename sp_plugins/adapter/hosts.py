"""The host registry: what the host-neutral adapter needs to know of each host, declared by the host.

A host adapter (``sp_plugins.nerfstudio``, ``sp_plugins.sdfstudio``, or a third one in its own
package) describes itself with one :class:`Host` value and registers it with one line, an entry
point of the group :data:`ENTRY_POINT_GROUP`::

    # pyproject.toml
    [project.entry-points."sp_plugins.hosts"]
    myhost = "my_package.sp_host:HOST"

(:func:`register` does the same at run time, for a host without a distribution of its own, such as
the tests' toy host). What the adapter then reads from the registry, instead of a list of its own:

- :func:`packages`: the top-level packages whose classes a saved run config may name (the safe
  config reader, :mod:`sp_plugins.adapter.safe_config`), and :func:`renamed`, the class paths a
  host renamed since an older release, so a run folder saved before still loads;
- :attr:`Host.flags`: the flag names a host's command line uses, for the one-line errors of the
  preflight checks (:mod:`sp_plugins.adapter.checks`, :mod:`sp_plugins.adapter.callbacks`);
- :attr:`Host.table`: the module holding the host's method knowledge (presets, refusals, read points);
- :attr:`Host.docs_page`: the docs page its generated method table lives in (:mod:`sp_plugins.method_table`).

Reading the registry imports each host's descriptor module only: no host package.
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass, field
from functools import lru_cache
from importlib.metadata import entry_points
from types import MappingProxyType
from typing import Any, Callable, Dict, Mapping, Optional, Tuple

__all__ = ["ENTRY_POINT_GROUP", "Flags", "Host", "get", "hosts", "packages", "register", "renamed", "renamed_attribute", "unregister"]

ENTRY_POINT_GROUP = "sp_plugins.hosts"


@dataclass(frozen=True)
class Flags:
    """The flags of a host's training command that our one-line errors name."""

    steps: str = "--max-num-iterations"
    """Sets the run's length."""
    device: str = "--machine.device-type"
    """Picks the device kind (cpu, cuda, mps)."""
    devices: str = "--machine.num-devices"
    """Sets how many devices train."""
    sp: str = "--pipeline.model.sp"
    """The prefix of SP's own flags (``<sp>.alpha0``)."""


def _always() -> bool:
    return True


@dataclass(frozen=True)
class Host:
    """One host as the adapter sees it (see the module docstring for who reads what)."""

    name: str
    """The host's name (``nerfstudio``, ``sdfstudio``)."""
    packages: Tuple[str, ...]
    """Top-level packages whose classes its saved run configs name."""
    table: str
    """Module path of its method table (the one file that knows methods)."""
    imports: Tuple[str, ...] = ()
    """Other top-level packages of the host that its adapter imports (sdfstudio's ``scripts``)."""
    flags: Flags = field(default_factory=Flags)
    docs_page: Optional[str] = None
    """The docs page (relative to a checkout's root) that holds its generated method table."""
    renamed: Mapping[str, str] = field(default_factory=dict)
    """Class paths renamed since an older release: old path -> new path (``module.QualName``)."""
    available: Callable[[], bool] = _always
    """True when the host is importable in this environment (no host module is imported to tell)."""

    def table_module(self):
        """The host's method table module (cheap: a table imports no host)."""
        return importlib.import_module(self.table)


_REGISTERED: Dict[str, Host] = {}


@lru_cache(maxsize=None)
def _from_entry_points() -> Tuple[Host, ...]:
    found = []
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            host = ep.load()
        except Exception as err:  # noqa: BLE001  (one broken host must not break the others)
            print(f"sp-plugins: skipping host {ep.name!r} ({ep.value}): {type(err).__name__}: {err}", file=sys.stderr)
            continue
        if not isinstance(host, Host) or host.name != ep.name:
            print(f"sp-plugins: skipping host {ep.name!r}: {ep.value} is not its Host", file=sys.stderr)
            continue
        found.append(host)
    return tuple(found)


def hosts() -> Dict[str, Host]:
    """Every registered host by name: the entry points', then those registered at run time."""
    return {**{h.name: h for h in _from_entry_points()}, **_REGISTERED}


def get(name: str) -> Host:
    """The host named ``name``; ``KeyError`` naming the registered ones otherwise."""
    known = hosts()
    if name not in known:
        raise KeyError(f"no host {name!r} is registered (registered: {', '.join(sorted(known)) or 'none'}); "
                       f"a host registers with an entry point of the group {ENTRY_POINT_GROUP!r}")
    return known[name]


def register(host: Host) -> Host:
    """Register ``host`` in this process (a host with no distribution of its own); returns it."""
    _REGISTERED[host.name] = host
    return host


def unregister(name: str) -> None:
    """Forget a host :func:`register` added."""
    _REGISTERED.pop(name, None)


def packages() -> Tuple[str, ...]:
    """``sp_plugins`` and every registered host's packages, each once, in order."""
    out = ["sp_plugins"]
    for host in hosts().values():
        out.extend(p for p in host.packages if p not in out)
    return tuple(out)


def renamed_attribute(module: str, name: str) -> Any:
    """A module's ``__getattr__`` for the names its host renamed (:attr:`Host.renamed`): the class now
    at the new path, so a ``config.yml`` saved before the rename still loads, with any YAML loader
    (the host's own commands included); ``AttributeError`` for any other name."""
    new = renamed().get(f"{module}.{name}")
    if new is None:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    new_module, _, attr = new.rpartition(".")
    return getattr(importlib.import_module(new_module), attr)


def renamed() -> Mapping[str, str]:
    """Every registered host's renamed class paths (old -> new)."""
    out: Dict[str, str] = {}
    for host in hosts().values():
        out.update(host.renamed)
    return MappingProxyType(out)
