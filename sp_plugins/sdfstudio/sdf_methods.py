"""Trainer configs of the sdfstudio SP methods (the ``method_configs.sdfstudio`` modules only pick one).

Each SP method is sdfstudio's own method config (trainer, data, optimizers, schedulers, field
sizes: everything as the host ships it), with the model and field config classes swapped for
ours and the paper's SP settings (Ling et al. 2025), schedule ends as fractions of training so
that shortened runs keep their shape:

- NeuS, neus-facto: alpha0 0.013, exponential to 0 over the first 20%.
- Neuralangelo, bakedangelo: alpha0 0.03 over the first 30%, coarse-to-fine replaced by SP; or a
  learnable alpha grid initialised to 0.03, Adam lr 1e-3 (``--pipeline.model.sp.alpha-grid True``;
  128^3 in the paper, ``alpha-grid-resolution`` 32 by default here to fit a CPU).

Alphas are in scene units (sdfstudio normalises scenes to the unit box / sphere).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Dict

from sp_plugins.adapter import presets
from sp_plugins.core import SPConfig
from sp_plugins.sdfstudio.callbacks import ALPHA_GRID_GROUP
from sp_plugins.sdfstudio.registration import MethodSpecification
from sp_plugins.sdfstudio.sdf_field import SPSDFFieldConfig

NEUS_SP = presets.NEUS
NEURALANGELO_SP = presets.NEURALANGELO


def convert(config: Any, cls: type, **changes: Any) -> Any:
    """``config`` as an instance of its subclass ``cls``: every init field copied except
    ``_target`` (``cls``'s own), then ``changes`` applied."""
    values: Dict[str, Any] = {
        f.name: copy.deepcopy(getattr(config, f.name))
        for f in dataclasses.fields(config)
        if f.init and f.name != "_target"
    }
    values.update(changes)
    return cls(**values)


def host_method_config(name: str):
    """A deep copy of sdfstudio's own config of method ``name``."""
    from nerfstudio.configs.method_configs import method_configs

    return copy.deepcopy(method_configs[name])


def final_fd_step(base: str, max_res: int) -> float:
    """Where sdfstudio's numerical-gradient step schedule ends (commit 370902a)."""
    return {"neuralangelo": 2.0 / max_res, "bakedangelo": 1.0 / max_res}[base]


def sp_method(base: str, model_config_cls: type, sp: SPConfig, description: str, *, replace_coarse_to_fine: bool = False) -> MethodSpecification:
    """``sp-<base>``: sdfstudio's method ``base`` with our model / field classes and ``sp``."""
    config = host_method_config(base)
    config.method_name = f"sp-{base}"
    model = config.pipeline.model
    field_changes: Dict[str, Any] = {}
    if replace_coarse_to_fine:
        field_changes["fd_step"] = final_fd_step(base, model.sdf_field.max_res)
    sdf_field = convert(model.sdf_field, SPSDFFieldConfig, **field_changes)
    model_changes: Dict[str, Any] = {}
    if replace_coarse_to_fine:
        model_changes.update(enable_progressive_hash_encoding=False, enable_numerical_gradients_schedule=False)
    config.pipeline.model = convert(model, model_config_cls, sdf_field=sdf_field, sp=copy.deepcopy(sp), **model_changes)
    from nerfstudio.engine.optimizers import AdamOptimizerConfig

    config.optimizers[ALPHA_GRID_GROUP] = {
        "optimizer": AdamOptimizerConfig(lr=sp.alpha_grid_lr, eps=1e-15),
        "scheduler": None,
    }
    return MethodSpecification(config=config, description=description)
