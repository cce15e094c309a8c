"""Shrink a trainer config to a CPU size, for tests and benchmarks of either host.

Both hosts' trainer configs (nerfstudio 1.x and sdfstudio's fork) have ``pipeline.model`` and
``optimizers`` of the same shape, so one function serves both; it imports no host.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional


def _set(target: Any, values: Mapping[str, Any], where: str) -> None:
    for key, value in values.items():
        if not hasattr(target, key):
            raise AttributeError(f"{where} has no setting {key!r} ({type(target).__name__})")
        setattr(target, key, value)


def shrink(
    config: Any,
    *,
    field: Optional[Mapping[str, Any]] = None,
    lr: Optional[Mapping[str, float]] = None,
    warm_up_end: Optional[int] = None,
    max_steps: Optional[int] = None,
    **model: Any,
) -> Any:
    """Shrink ``config`` in place to a CPU size: ``model`` settings go on ``config.pipeline.model``,
    ``field`` ones on its field config (``sdf_field`` for SDF methods), ``lr`` maps optimizer groups to
    learning rates, and ``warm_up_end`` / ``max_steps`` go on those groups' schedulers. A setting the
    config does not have is an error (a misspelt one would otherwise shrink nothing).

        shrink(config, num_samples=16, field=dict(hidden_dim=32, max_res=64),
               lr={"fields": 5e-3, "field_grid": 1e-2}, warm_up_end=10, max_steps=200)

    Works on any trainer config with ``pipeline.model`` and ``optimizers`` (sdfstudio's too)."""
    target = config.pipeline.model
    _set(target, model, "pipeline.model")
    if field:
        name = "sdf_field" if hasattr(target, "sdf_field") else "field"
        _set(getattr(target, name), field, f"pipeline.model.{name}")
    for group, rate in (lr or {}).items():
        if group not in config.optimizers:
            raise KeyError(f"no optimizer group {group!r}; the config has {', '.join(config.optimizers)}")
        entry = config.optimizers[group]
        entry["optimizer"].lr = rate
        schedule = {k: v for k, v in (("warm_up_end", warm_up_end), ("max_steps", max_steps)) if v is not None}
        if schedule:
            _set(entry["scheduler"], schedule, f"optimizers[{group!r}].scheduler")
    return config
