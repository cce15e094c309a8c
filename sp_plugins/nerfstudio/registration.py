"""How SP methods reach nerfstudio's commands: ``with_sp`` for any method, and what ``sp-train`` offers.

``with_sp(spec)`` returns the ``sp-<name>`` variant of any registered method (nerfstudio's own or
another plugin's): the same trainer config, with the model config converted to its SP variant
(:mod:`sp_plugins.nerfstudio.variants`), which adds ``--pipeline.model.sp.*`` and leaves every
other flag as it was, plus the optimizer entry a learnable alpha grid needs. A plugin author
registers an SP variant of their method with one entry point::

    # pyproject.toml: [project.entry-points."nerfstudio.method_configs"]
    # sp-mymethod = "my_plugin.sp:sp_mymethod"
    from sp_plugins.nerfstudio import with_sp
    sp_mymethod = with_sp(mymethod)

:func:`sp_methods` is every registered method's SP variant, or why it is refused (:func:`refusal`),
for the ``sp-train`` command (:mod:`sp_plugins.cli.train`). This module is cheap to import and
changes nothing in the process.
"""

from __future__ import annotations

import copy
from typing import Any, Dict, Optional, Tuple

from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, alpha_grid_optimizer
from sp_plugins.adapter.variants import convert, refuse_or_switch_on, target_class
from sp_plugins.core import SPConfig
from sp_plugins.nerfstudio import table
from sp_plugins.nerfstudio.table import preset_for, refusal
from sp_plugins.nerfstudio.variants import variant

__all__ = ["preset_for", "refusal", "sp_methods", "with_sp"]


def with_sp(spec: Any, sp: Optional[SPConfig] = None, *, name: Optional[str] = None, description: Optional[str] = None):
    """The SP variant of method ``spec`` (a ``MethodSpecification`` or a ``TrainerConfig``).

    ``sp`` defaults to :func:`preset_for` the host model; ``name`` to ``sp-<method name>``.
    A method that is already ours (its model config has ``sp``) comes back with SP enabled.
    Raises ``ValueError`` naming the reason when SP cannot reach the method."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.plugins.types import MethodSpecification

    from sp_plugins.nerfstudio.components.parallel_data import repeatable_datamanager  # defers nerfstudio
    from sp_plugins.nerfstudio.components.schedulers import with_float_schedulers  # defers nerfstudio
    from sp_plugins.nerfstudio.components.trainer import checked  # defers nerfstudio

    config = checked(copy.deepcopy(spec.config if isinstance(spec, MethodSpecification) else spec))  # ns-train checks before writing
    base_description = getattr(spec, "description", "") or config.method_name
    model = config.pipeline.model
    if not refuse_or_switch_on(config.method_name, model, refusal(config), sp):
        sp_config = copy.deepcopy(sp) if sp is not None else variant("Model", target_class(model)).sp_preset(model)
        config_cls = variant("ModelConfig", type(model))
        config.pipeline.model = convert(model, config_cls, _target=variant("Model", target_class(model)), sp=sp_config)
    config.method_name = name or (config.method_name if config.method_name.startswith("sp-") else f"sp-{config.method_name}")
    config.optimizers[ALPHA_GRID_GROUP] = alpha_grid_optimizer(config.pipeline.model.sp, AdamOptimizerConfig)
    with_float_schedulers(config.optimizers)  # the host's numpy learning rates break torch.load in ns-eval
    repeatable_datamanager(config.pipeline.datamanager)  # nerfstudio's ray workers never see the trainer's seed
    text = description or f"{base_description} + stochastic preconditioning of the sample positions (sp-plugins)."
    return MethodSpecification(config=config, description=text)


def sp_methods(methods: Dict[str, Any], descriptions: Dict[str, str]) -> Tuple[Dict[str, Any], Dict[str, str], Dict[str, str]]:
    """``(configs, descriptions, refused)`` of ``sp-train``: for every method, its SP variant's
    trainer config, or why it is refused. Our own baselines are refused with their SP method's name."""
    configs: Dict[str, Any] = {}
    texts: Dict[str, str] = {}
    refused: Dict[str, str] = {}
    for method, config in methods.items():
        model = getattr(getattr(config, "pipeline", None), "model", None)
        sp = getattr(model, "sp", None)
        if isinstance(sp, SPConfig) and not sp.enabled and method not in table.SP_OFF_METHODS:
            counterpart = table.OUR_BASELINES.get(method, f"sp-{method}")
            refused[method] = f"it is the baseline of {counterpart}, the method with SP; train that one"
            continue
        reason = refusal(config)
        if reason:
            refused[method] = reason
            continue
        try:  # the method keeps its name: ns-eval / ns-render / ns-export look its data manager up by it
            spec = with_sp(config, name=config.method_name, description=descriptions.get(method, ""))
        except ValueError as err:
            refused[method] = str(err)
            continue
        configs[method] = spec.config
        texts[method] = spec.description
    return configs, texts, refused
