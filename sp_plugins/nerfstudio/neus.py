"""NeuS and Neuralangelo-lite models with the shared SP settings.

- :class:`SPNeuSModel`: nerfstudio's NeuS on our SDF field (:mod:`sp_plugins.nerfstudio.sdf_field`:
  masked hash levels, numerical gradients), SP through the one seam like every method;
  ``sp.enabled=False`` is the plain baseline. The cosine
  annealing of NeuS ends at a fraction of training instead of a fixed 50k steps, so short runs
  anneal too. Rays that miss the scene box keep their background in front of its far plane
  (:mod:`sp_plugins.nerfstudio.components.colliders`: nerfstudio's turned such a ray's colour NaN).
- :class:`NeuralangeloLiteModel`: the same with a hash grid, numerical gradients, an eikonal and a
  curvature loss, and Neuralangelo's coarse-to-fine scheme (:func:`coarse_to_fine_schedule`).
  ``coarse_to_fine=False`` uses all levels and the finest step from step 0 (what the SP variant
  does), with the curvature weight Neuralangelo reaches once all levels are on.

Neuralangelo's schedule (its paper, Sec. 3.2-3.3, and NVlabs/neuralangelo's trainer), and ours:

- warm-up: for the first ``c2f_warmup`` steps (Neuralangelo: its learning-rate warm-up, 5000 of
  500k) the curvature weight ramps linearly from 0 and no level is added;
- then one level is added every ``(c2f_end - c2f_warmup) / (levels - c2f_init_levels)`` steps
  (Neuralangelo: every 5000 steps from 4 levels, so all 16 are on at 65k = ``c2f_end`` 0.13);
- the numerical-gradient step is ``1 / resolution`` of the finest active level, in scene units
  (grid over [-2, 2]: a quarter of that level's cell), from the coarsest level on; the 4-point
  stencil divides it by sqrt(3) so its tetrahedron vertices lie at that distance, as Neuralangelo's;
- after warm-up the curvature weight is ``curvature_loss_mult / growth ** (active - init)``
  (``growth`` = the grid's per-level scale).

Differences kept, and why: during warm-up Neuralangelo's code computes ``init + (step - warm-up) //
interval`` with integer division, which gives ``init - 1`` levels (3, not the configured 4) until
warm-up ends; we keep the configured ``c2f_init_levels`` (the floor of a negative number is an
artefact, not a documented choice). Warm-up and level interval are fractions of training, so
short runs follow the same shape; Neuralangelo's steps are absolute.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, NamedTuple, Optional, Type

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.models.neus import NeuSModel, NeuSModelConfig

from sp_plugins.nerfstudio.components import hash_encoding
from sp_plugins.nerfstudio.components.colliders import bound_surface_rays
from sp_plugins.adapter.callbacks import model_schedule_callback
from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio.model import SPModel, SPModelConfig
from sp_plugins.nerfstudio.sdf_field import LAPLACIAN, CoarseToFineSDFField, CoarseToFineSDFFieldConfig
from sp_plugins.patches.nerfstudio_marching_cubes import hold_for


GRID_GROUP = "field_grid"
"""Optimizer group of the SDF field's hash-grid tables (``--optimizers.field-grid.*``)."""


def _steps(fraction_or_steps: float, total: int) -> int:
    """A fraction of training (<= 1) or an absolute step count (> 1) as steps."""
    return max(1, round(fraction_or_steps * total)) if fraction_or_steps <= 1 else int(fraction_or_steps)


@dataclass
class SPNeuSModelConfig(SPModelConfig, NeuSModelConfig):
    """NeuS with stochastic preconditioning at the SDF field's queries."""

    _target: Type = field(default_factory=lambda: SPNeuSModel)
    sdf_field: CoarseToFineSDFFieldConfig = field(default_factory=CoarseToFineSDFFieldConfig)
    """The SDF field (NeuS: frequency encoding only; hash grid with use_grid_feature)."""
    cos_anneal_end: float = 0.5
    """NeuS cosine annealing reaches 1 here: a fraction of training (<= 1) or a step count."""
    background_mlp_layers: int = 8
    """Layers of the NeRF++ background MLP (``background_model mlp``; nerfstudio's is 8 x 256)."""
    background_mlp_width: int = 256
    """Width of the NeRF++ background MLP. On a CPU the 8 x 256 background costs more than the whole
    foreground of a small hash-grid NeuS (measured: about 40% of a step in matrix products); a
    narrower one (e.g. 4 x 64) keeps a background model affordable."""


class SPNeuSModel(SPModel, NeuSModel):
    config: SPNeuSModelConfig
    field: CoarseToFineSDFField

    def populate_modules(self) -> None:
        super().populate_modules()
        hold_for(self)  # without CUDA: ns-export marching-cubes builds this model, then meshes our field on the CPU

    def populate_host_modules(self) -> None:
        super().populate_host_modules()
        bound_surface_rays(self)  # rays missing the box made the background NaN (colliders.py)
        self._size_background_mlp()
        device = self.kwargs.get("device")
        if self.config.background_model == "grid" and hash_encoding.use_sp_hash_grids(device):
            # the host's background grid is nerfstudio's slow torch HashEncoding without tcnn
            hash_encoding.setup_host_modules(self.field_background, self.__class__.__name__, device)

    def _size_background_mlp(self) -> None:
        """Rebuild the host's NeRF++ background MLP at the configured size (the host's own when unchanged)."""
        layers, width = self.config.background_mlp_layers, self.config.background_mlp_width
        if self.config.background_model != "mlp" or (layers, width) == (8, 256):
            return
        if layers < 1 or width < 1:
            raise InputError(f"background_mlp_layers and background_mlp_width must be >= 1, got {layers} and {width}.")
        from nerfstudio.fields.vanilla_nerf_field import NeRFField

        host = self.field_background
        self.field_background = NeRFField(
            position_encoding=host.position_encoding,
            direction_encoding=host.direction_encoding,
            base_mlp_num_layers=layers,
            base_mlp_layer_width=width,
            head_mlp_layer_width=min(128, width),
            skip_connections=(4,) if layers > 4 else (),
            spatial_distortion=host.spatial_distortion,
        )

    def get_param_groups(self) -> Dict[str, List[torch.nn.Parameter]]:
        """With a hash grid, its tables get their own optimizer group (:data:`GRID_GROUP`), so the
        grid's and the MLPs' learning rates can differ (the paper sweeps both); the trainer configs
        give both groups the same settings by default."""
        groups = super().get_param_groups()
        grid = list(self.field.encoding.parameters()) if self.config.sdf_field.use_grid_feature else []
        if grid:
            ids = {id(p) for p in grid}
            groups["fields"] = [p for p in groups["fields"] if id(p) not in ids]
            groups[GRID_GROUP] = grid
        return groups

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        total = self.sp_run_length(training_callback_attributes).total
        if total is not None:
            self.anneal_end = _steps(self.config.cos_anneal_end, total)
        return super().get_training_callbacks(training_callback_attributes)


@dataclass
class NeuralangeloLiteModelConfig(SPNeuSModelConfig):
    """Neuralangelo on NeuS's renderer: hash grid, numerical gradients, curvature loss, coarse-to-fine."""

    _target: Type = field(default_factory=lambda: NeuralangeloLiteModel)
    sdf_field: CoarseToFineSDFFieldConfig = field(
        default_factory=lambda: CoarseToFineSDFFieldConfig(
            use_grid_feature=True, numerical_gradients=True, num_layers=2, num_layers_color=2, hidden_dim=256, geo_feat_dim=256
        )
    )
    eikonal_loss_mult: float = 0.1
    curvature_loss_mult: float = 5e-4
    """Weight of the mean |Laplacian| at the end of warm-up; divided by the grid's growth factor
    for every level added after it (Neuralangelo)."""
    c2f_warmup: float = 0.01
    """Warm-up (Neuralangelo: 5000 of 500k steps): the curvature weight ramps up linearly and no
    level is added until here. A fraction of training (<= 1) or a step count."""
    coarse_to_fine: bool = True
    """Switch grid levels on progressively and shrink the finite-difference step with them."""
    c2f_init_levels: int = 4
    """Active grid levels until the end of warm-up (Neuralangelo: 4)."""
    c2f_end: float = 0.13
    """All levels are active from here on (Neuralangelo: 5000 + 12 x 5000 = 65k of 500k): a
    fraction of training or a step count; levels are added evenly between warm-up and here."""

    def __post_init__(self) -> None:
        if not 1 <= self.c2f_init_levels <= self.sdf_field.num_levels:
            raise ValueError(f"c2f_init_levels={self.c2f_init_levels}: must be in [1, num_levels={self.sdf_field.num_levels}]")
        if not (self.sdf_field.use_grid_feature and self.sdf_field.numerical_gradients):
            raise ValueError("neuralangelo-lite needs sdf_field.use_grid_feature=True and numerical_gradients=True")


class CoarseToFine(NamedTuple):
    """Neuralangelo's schedule at one step."""

    active_levels: int
    added_levels: int
    """Levels added since warm-up ended (the exponent of the curvature weight's decay)."""
    warmup: float
    """Curvature warm-up factor in [0, 1]."""


def coarse_to_fine_schedule(step: int, warmup_steps: int, end_steps: int, init_levels: int, num_levels: int) -> CoarseToFine:
    """Levels and warm-up at ``step``: ``init_levels`` until ``warmup_steps``, then evenly more
    until all ``num_levels`` are on at ``end_steps`` (at once when ``end_steps <= warmup_steps``,
    as in a run of a few steps); the warm-up factor ramps 0 -> 1 over ``warmup_steps``."""
    warm = min(1.0, step / warmup_steps) if warmup_steps > 0 else 1.0
    if step < warmup_steps or init_levels >= num_levels:
        return CoarseToFine(init_levels, 0, warm)
    interval = (end_steps - warmup_steps) / (num_levels - init_levels)
    added = num_levels - init_levels if interval <= 0 else min(num_levels - init_levels, int((step - warmup_steps) // interval))
    return CoarseToFine(init_levels + added, added, warm)


class NeuralangeloLiteModel(SPNeuSModel):
    config: NeuralangeloLiteModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        self.curvature_mult = 0.0
        self.coarse_to_fine_at(0, None)

    def level_fd_step(self, level: int) -> float:
        """Neuralangelo's numerical-gradient step for ``level``: ``1 / resolution`` in scene
        units, per axis for the 6-point stencil, along the tetrahedron's vertices for the 4-point one.
        The resolution is the grid's vertices per axis (tcnn's; Neuralangelo's own list,
        ``floor(base * growth**l) + 1``, differs by one where ``base * growth**l`` is an integer)."""
        eps = 1.0 / self.field.encoding.levels[level].resolution
        return eps / math.sqrt(3.0) if self.config.sdf_field.stencil == "4pt" else eps

    def coarse_to_fine_at(self, step: int, total: Optional[int]) -> CoarseToFine:
        """Set active levels, finite-difference step and curvature weight for ``step``."""
        c = self.config
        levels = c.sdf_field.num_levels
        if not c.coarse_to_fine:
            warm = 1.0 if total is None else min(1.0, step / _steps(c.c2f_warmup, total))
            state = CoarseToFine(levels, levels - c.c2f_init_levels, warm)
        elif total is None:  # before training knows its length (a restored checkpoint sets the buffers)
            state = CoarseToFine(c.c2f_init_levels, 0, 1.0)
        else:
            warmup_steps, end_steps = _steps(c.c2f_warmup, total), _steps(c.c2f_end, total)
            if end_steps <= warmup_steps and (c.c2f_end <= 1) == (c.c2f_warmup <= 1) and c.c2f_end > c.c2f_warmup:
                end_steps = warmup_steps + 1  # a run so short that rounding merged two ordered fractions
            state = coarse_to_fine_schedule(step, warmup_steps, end_steps, c.c2f_init_levels, levels)
        self.field.set_active_levels(state.active_levels)
        fd = c.sdf_field.fd_step if c.sdf_field.fd_step is not None else self.level_fd_step(state.active_levels - 1)
        self.field.set_fd_step(fd)
        growth = self.field.encoding.per_level_scale
        self.curvature_mult = c.curvature_loss_mult * state.warmup / growth**state.added_levels
        return state

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        return callbacks + [model_schedule_callback(self.coarse_to_fine_at, self.sp_run_length(training_callback_attributes),
                                                   self.sp_training_callback)]

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        losses = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training and self.curvature_mult > 0:
            lap = outputs["field_outputs"].get(LAPLACIAN)
            if lap is not None:
                losses["curvature_loss"] = lap.abs().mean() * self.curvature_mult
        return losses

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        metrics = super().get_metrics_dict(outputs, batch)
        if self.training:
            metrics["active_levels"] = self.field.encoding.active_levels  # Python mirrors: no GPU sync per step
            metrics["fd_step"] = self.field._fd_step
        return metrics


__all__ = [
    "GRID_GROUP",
    "CoarseToFine",
    "NeuralangeloLiteModel",
    "NeuralangeloLiteModelConfig",
    "SPNeuSModel",
    "SPNeuSModelConfig",
    "coarse_to_fine_schedule",
]
