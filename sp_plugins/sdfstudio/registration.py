"""How SP methods reach sdfstudio's commands: ``with_sp`` for any SDF method, our entry-point
group, and ``sp-<method>`` for every method sdfstudio registers; the names of
:mod:`sp_plugins.nerfstudio.registration` (``with_sp``, :func:`refusal`, :func:`preset_for`,
:func:`sp_methods`). What is known about single methods, and the rules and presets, are in :mod:`sp_plugins.sdfstudio.table`.

``with_sp(config)`` turns sdfstudio's own config of a method into ``sp-<method>``
(:func:`sp_plugins.sdfstudio.conversion.sp_model_config`); a method that is already ours comes back
with SP on. Methods SP cannot reach are refused with "SP cannot be put on <method>: <reason>"
(:func:`refusal`).

sdfstudio (commit 370902a) has no plugin mechanism: ``nerfstudio/configs/method_configs.py``
fills a plain dict and builds a tyro union from it at import, and ``scripts/train.py`` copies that
union at its own import. :func:`add_methods` puts every method of the group
``sp_plugins.sdfstudio_methods`` into the dict (sp-neus, sp-neus-facto, sp-neuralangelo,
sp-bakedangelo: names and presets fixed), then ``sp-<method>`` for every other registered method
SP applies to (:func:`sp_methods`), remembers why the rest are refused (:data:`REFUSED`), and
rebuilds the union in both modules, which is enough as long as it runs before ``tyro.cli`` (our
``sp-sdfstudio-train`` calls it first thing; the opt-in hook of :mod:`sp_plugins.sdfstudio.hook`
right after ``scripts.train`` is imported). Unlike ``sp-train``, the SP methods get their own
``sp-`` names: they sit in the one dict next to the host's.

A method whose module fails to import is skipped with one line on stderr, so one broken
method never breaks the others. Cheap to import: the host loads on use.
"""

from __future__ import annotations

import copy
import sys
from dataclasses import dataclass
from importlib.metadata import entry_points
from types import ModuleType
from typing import TYPE_CHECKING, Any, Dict, Optional, Tuple

from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, alpha_grid_optimizer
from sp_plugins.adapter.variants import refuse_or_switch_on, target_class
from sp_plugins.sdfstudio.conversion import describe, sp_model_config
from sp_plugins.sdfstudio.table import preset_for, refusal, replaces_coarse_to_fine

__all__ = ["ENTRY_POINT_GROUP", "MethodSpecification", "REFUSED", "add_methods", "preset_for", "refusal", "sp_method",
           "sp_methods", "with_sp"]

if TYPE_CHECKING:
    from sp_plugins.core import SPConfig

ENTRY_POINT_GROUP = "sp_plugins.sdfstudio_methods"
PREFIX = "sp-"

REFUSED: Dict[str, str] = {}
"""``sp-<method>`` -> why SP cannot be put on that registered method (filled by :func:`add_methods`)."""


@dataclass
class MethodSpecification:
    """What each entry point of the group names: an sdfstudio ``Config`` and a one-line description."""

    config: Any
    description: str


def with_sp(spec: Any, sp: Optional["SPConfig"] = None, *, name: Optional[str] = None, description: Optional[str] = None) -> MethodSpecification:
    """The SP variant of method ``spec`` (a :class:`MethodSpecification` or an sdfstudio ``Config``).

    ``sp`` defaults to :func:`preset_for` the host model config; ``name`` to ``sp-<method name>``.
    A method that is already ours (its model config has ``sp``) comes back with SP enabled (an
    explicit ``sp`` wins). Raises ``ValueError`` naming the reason when SP cannot reach the method."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig

    from sp_plugins.sdfstudio.variants import variant  # defers sdfstudio

    config = copy.deepcopy(spec.config if isinstance(spec, MethodSpecification) else spec)
    base = config.method_name
    model = config.pipeline.model
    if refuse_or_switch_on(config.method_name, model, refusal(config), sp):
        text = (spec.description if isinstance(spec, MethodSpecification) else "") or f"sdfstudio {base} {describe(model.sp, False)}."
    else:
        sp = copy.deepcopy(sp) if sp is not None else variant("Model", target_class(model)).sp_preset(model)
        config.pipeline.model = sp_model_config(model, sp)
        text = f"sdfstudio {base} {describe(sp, replaces_coarse_to_fine(model))}."
    config.method_name = name or (base if base.startswith(PREFIX) else f"{PREFIX}{base}")
    config.optimizers[ALPHA_GRID_GROUP] = alpha_grid_optimizer(config.pipeline.model.sp, AdamOptimizerConfig)
    return MethodSpecification(config=config, description=description or text)


def host_method_config(name: str) -> Any:
    """A deep copy of sdfstudio's own config of method ``name``."""
    from nerfstudio.configs.method_configs import method_configs

    return copy.deepcopy(method_configs[name])


def sp_method(base: str, sp: Optional["SPConfig"] = None, description: Optional[str] = None) -> MethodSpecification:
    """``sp-<base>`` from sdfstudio's registered method ``base`` (for :mod:`sp_plugins.method_configs.sdfstudio`)."""
    return with_sp(host_method_config(base), sp, description=description)


def sp_methods(method_configs: Dict[str, Any], descriptions: Dict[str, str]) -> Tuple[Dict[str, Any], Dict[str, str], Dict[str, str]]:
    """``(configs, descriptions, refused)``, keyed by SP method name (``sp-<method>``): for every
    host method, its SP config or why it is refused. Methods that are already ours are skipped
    (they are in the dict under their own names)."""
    configs: Dict[str, Any] = {}
    texts: Dict[str, str] = {}
    refused: Dict[str, str] = {}
    for method, config in method_configs.items():
        if hasattr(getattr(getattr(config, "pipeline", None), "model", None), "sp"):
            continue  # ours
        name = f"{PREFIX}{method}"
        reason = refusal(config)
        if reason:
            refused[name] = reason
            continue
        host_text = descriptions.get(method, "").rstrip(".")
        spec = with_sp(config, name=name)
        sp = spec.config.pipeline.model.sp
        configs[name] = spec.config
        texts[name] = f"{host_text} ({method}) {describe(sp, replaces_coarse_to_fine(config.pipeline.model))}." if host_text else spec.description
    return configs, texts, refused


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
