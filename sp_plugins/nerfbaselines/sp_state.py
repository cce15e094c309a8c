"""What a run did about SP, checked against what its method id promises, and recorded with its results.

A results table compares ``X+sp`` with ``X+sp-off`` by their ids; what builds each run is a flag in
:data:`sp_plugins.nerfbaselines.specs.ENTRIES`. Were the flags wrong (swapped, say), both rows would
train and the table would compare the wrong runs without a sign. So the promise is read from the id
itself (``+sp``: SP on and attached to a field; ``+sp-off``: SP off; a plain id: as its config says),
the built model is asked what it does, and a run whose model breaks the promise stops before its
first step (:class:`SPStateError`). What the model does is also written into the method's
``hparams`` (``sp_run.enabled``, ``sp_run.alpha0``, ``sp_run.fields``), which nerfbaselines saves in
each checkpoint's ``nb-info.json`` and ``results-N.json``, so a table can be checked from its files.
"""

from __future__ import annotations

from typing import Any, Dict

from sp_plugins.adapter.field import SPFieldMixin
from sp_plugins.core import StochasticPreconditioner
from sp_plugins.nerfbaselines.specs import SP_OFF_SUFFIX, SP_SUFFIX

__all__ = ["PREFIX", "SPStateError", "as_hparams", "check", "config_enabled", "model_state", "promised", "twin"]

PREFIX = "sp_run."
"""The hparams keys this module writes start with it."""


class SPStateError(RuntimeError):
    """A built model whose SP state is not the one its method id promises (one line)."""


def config_enabled(config: Any) -> bool:
    """SP's ``enabled`` in a trainer config (False for a model without SP settings)."""
    return bool(getattr(getattr(config.pipeline.model, "sp", None), "enabled", False))


def promised(method_id: str, config: Any) -> bool:
    """Whether a run of ``method_id`` must train with SP: the suffix says, not the spec's flags; a
    plain id (``sp-nerfacto``, ``neus-hashgrid``, ``mipnerf``) as its config says."""
    if method_id.endswith(SP_OFF_SUFFIX):
        return False
    if method_id.endswith(SP_SUFFIX):
        return True
    return config_enabled(config)


def twin(method_id: str) -> str:
    """The id of the same method with SP the other way (``X+sp`` <-> ``X+sp-off``)."""
    if method_id.endswith(SP_OFF_SUFFIX):
        return method_id[: -len(SP_OFF_SUFFIX)] + SP_SUFFIX
    return method_id[: -len(SP_SUFFIX)] + SP_OFF_SUFFIX


def model_state(model: Any) -> Dict[str, Any]:
    """What SP does in the built ``model``: ``enabled``, ``alpha0`` (in scene units; None with SP off,
    where it acts on nothing) and the ``fields`` it is attached to (module names; with SP off they
    may still carry the inert seam)."""
    sp = getattr(model, "sp", None)
    if not isinstance(sp, StochasticPreconditioner):
        return {"enabled": False, "alpha0": None, "fields": []}
    enabled = bool(sp.config.enabled)
    scale = sp.scene_diagonal if sp.scene_diagonal is not None else 1.0
    fields = [name for name, module in model.named_modules() if isinstance(module, SPFieldMixin) and module.sp is sp]
    return {"enabled": enabled, "alpha0": float(sp.config.alpha0) * scale if enabled else None, "fields": fields}


def check(method_id: str, promise: bool, state: Dict[str, Any]) -> None:
    """Raise :class:`SPStateError` unless ``state`` keeps ``promise`` (SP on means attached to a field too)."""
    said = "on" if promise else "off"
    where = "its spec (sp_plugins.nerfbaselines.specs.ENTRIES) builds another run than its id names"
    if state["enabled"] != promise:
        raise SPStateError(f"{method_id} promises SP {said}, but the model it built has SP "
                           f"{'on' if state['enabled'] else 'off'}: {where}; its results would fill the wrong table row")
    if promise and not state["fields"]:
        raise SPStateError(f"{method_id} promises SP on, but SP is attached to no field of the model it built: {where}")


def as_hparams(state: Dict[str, Any]) -> Dict[str, Any]:
    """``state`` as hparams entries of simple types (nerfbaselines writes them with the results)."""
    entries = {f"{PREFIX}enabled": state["enabled"], f"{PREFIX}fields": ",".join(state["fields"])}
    if state["alpha0"] is not None:
        entries[f"{PREFIX}alpha0"] = state["alpha0"]
    return entries
