"""Our sdfstudio methods, added to ns-train: the entry-point group of our own, plus ``sp-<method>``
for every SDF method sdfstudio registers.

sdfstudio (commit 370902a) has no plugin mechanism: ``nerfstudio/configs/method_configs.py``
fills a plain dict and builds a tyro union from it at import, and ``scripts/train.py`` copies that
union at its own import. :func:`add_methods` puts every method of the group
``sp_plugins.sdfstudio_methods`` into the dict (sp-neus, sp-neus-facto, sp-neuralangelo,
sp-bakedangelo: names and presets fixed), then ``sp-<method>`` for every other registered method
SP applies to (:func:`sp_plugins.sdfstudio.sdf_methods.sp_methods`), remembers why the rest are
refused (:data:`REFUSED`), and rebuilds the union in both modules, which is enough as long as it
runs before ``tyro.cli`` (our ``sp-sdfstudio-train`` calls it first thing; the opt-in hook of
:mod:`sp_plugins.sdfstudio.hook` right after ``scripts.train`` is imported).

A method whose module fails to import is skipped with one line on stderr, so one broken
method never breaks the others.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any, Dict, Optional

ENTRY_POINT_GROUP = "sp_plugins.sdfstudio_methods"

REFUSED: Dict[str, str] = {}
"""``sp-<method>`` -> why SP cannot be put on that registered method (filled by :func:`add_methods`)."""


@dataclass
class MethodSpecification:
    """What each entry point of the group names: an sdfstudio ``Config`` and a one-line description."""

    config: Any
    description: str


def discover() -> Dict[str, MethodSpecification]:
    """Every method of :data:`ENTRY_POINT_GROUP`, by name (broken ones reported and skipped)."""
    methods: Dict[str, MethodSpecification] = {}
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            spec = ep.load()
        except Exception as err:  # noqa: BLE001  (one broken plugin must not break ns-train)
            print(f"sp-plugins: skipping sdfstudio method {ep.name!r} ({ep.value}): {type(err).__name__}: {err}", file=sys.stderr)
            continue
        if not isinstance(spec, MethodSpecification) or spec.config.method_name != ep.name:
            print(f"sp-plugins: skipping sdfstudio method {ep.name!r}: {ep.value} is not its MethodSpecification", file=sys.stderr)
            continue
        methods[ep.name] = spec
    return methods


def config_union(method_configs: Dict[str, Any], descriptions: Dict[str, str]):
    """The tyro union sdfstudio's ``method_configs.py`` builds, over ``method_configs``."""
    import tyro

    return tyro.conf.SuppressFixed[
        tyro.conf.FlagConversionOff[tyro.extras.subcommand_type_from_defaults(defaults=method_configs, descriptions=descriptions)]
    ]


def add_methods(train_module: Optional[ModuleType] = None) -> Dict[str, MethodSpecification]:
    """Add our methods to sdfstudio's method dict and rebuild its union (also in ``scripts.train``).
    Returns the methods added (entry points first, then the generic ``sp-<method>``); safe to call again."""
    import nerfstudio.configs.method_configs as host

    from sp_plugins.sdfstudio.sdf_methods import sp_methods

    methods = discover()
    # an entry point of that name wins (fixed preset and description); one made by an earlier call stays
    pending = {m: c for m, c in host.method_configs.items() if f"sp-{m}" not in methods and f"sp-{m}" not in host.method_configs}
    configs, texts, refused = sp_methods(pending, host.descriptions)
    for name, config in configs.items():
        methods[name] = MethodSpecification(config=config, description=texts[name])
    for name, spec in methods.items():
        host.method_configs[name] = spec.config
        host.descriptions[name] = spec.description
    REFUSED.clear()
    REFUSED.update({name: why for name, why in refused.items() if name not in host.method_configs})
    host.AnnotatedBaseConfigUnion = config_union(host.method_configs, host.descriptions)
    train = train_module if train_module is not None else sys.modules.get("scripts.train")
    if train is not None:
        train.AnnotatedBaseConfigUnion = host.AnnotatedBaseConfigUnion
    return methods
