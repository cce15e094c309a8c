"""What builds the SP method configs of sdfstudio: sdfstudio's own config of a method, converted.

:func:`sp_model_config` turns a host model config (trainer, data, optimizers, schedulers, field
sizes stay as the host ships them) into the SP variant of its own class
(:mod:`sp_plugins.sdfstudio.variants`), its ``sdf_field`` an
:class:`~sp_plugins.sdfstudio.seam.SeamSDFFieldConfig`. ``with_sp``, the refusals, the presets and
``sp_method`` (our four named methods in :mod:`sp_plugins.method_configs.sdfstudio`) are in
:mod:`sp_plugins.sdfstudio.registration`, which imports this module (never the other way round).
The host loads on use (:func:`sp_model_config`), so importing this module stays cheap.

Where the host enables Neuralangelo's progressive hash encoding (neuralangelo, bakedangelo,
neus-facto-angelo) SP *replaces* coarse-to-fine, as in the paper: all hash levels from step 0,
and the finite-difference step fixed at the value sdfstudio's schedule ends on
(``table.FINAL_FD_STEP``). The curvature-loss weight schedule (a loss weight, not a representation
schedule) is kept. Alphas are in scene units (sdfstudio normalises scenes to the unit box / sphere).
"""

from __future__ import annotations

import copy
from typing import Any, Dict, Optional

from sp_plugins.adapter.tables import lookup
from sp_plugins.adapter.variants import convert, target_class
from sp_plugins.core import SPConfig
from sp_plugins.sdfstudio.table import FINAL_FD_STEP, replaces_coarse_to_fine

__all__ = ["describe", "final_fd_step", "replaces_coarse_to_fine", "sp_model_config"]


def final_fd_step(model: type, max_res: int) -> Optional[float]:
    """Where sdfstudio's numerical-gradient step schedule ends for ``model`` (None: not known)."""
    found = lookup(FINAL_FD_STEP, model)
    return found[1] / max_res if found else None


def sp_model_config(model_config: Any, sp: SPConfig) -> Any:
    """The SP variant of an sdfstudio SDF model config, with ``sp`` (coarse-to-fine replaced where
    the host enables it)."""
    from sp_plugins.sdfstudio.seam import SeamSDFFieldConfig  # defers sdfstudio
    from sp_plugins.sdfstudio.variants import variant  # defers sdfstudio

    model = target_class(model_config)
    assert model is not None
    field_changes: Dict[str, Any] = {}
    model_changes: Dict[str, Any] = {}
    if replaces_coarse_to_fine(model_config):
        model_changes["enable_progressive_hash_encoding"] = False
        fd_step = final_fd_step(model, model_config.sdf_field.max_res)
        if getattr(model_config, "enable_numerical_gradients_schedule", False) and fd_step is not None:
            model_changes["enable_numerical_gradients_schedule"] = False
            field_changes["fd_step"] = fd_step
    sdf_field = convert(model_config.sdf_field, SeamSDFFieldConfig, **field_changes)
    return convert(
        model_config,
        variant("ModelConfig", type(model_config)),
        _target=variant("Model", model),
        sdf_field=sdf_field,
        sp=copy.deepcopy(sp),
        **model_changes,
    )


def describe(sp: SPConfig, replaced: bool) -> str:
    """What SP does to the method, for its ``ns-train`` description."""
    what = f"alpha0 {sp.alpha0:g}, to 0 over the first {sp.end:.0%}" if sp.end <= 1 else f"alpha0 {sp.alpha0:g}, to 0 by step {sp.end:g}"
    return ("coarse-to-fine replaced by stochastic preconditioning" if replaced else "+ stochastic preconditioning") + f" ({what})"
