"""Trainer configs of the SDF methods (:mod:`sp_plugins.method_configs.nerfstudio` only picks one each).

Paper settings (Ling et al. 2025) kept as defaults, with schedule ends as fractions of training so
that shortened runs keep their shape:

- NeuS, NeuS-hashgrid: 100k steps; alpha0 0.013, exponential to 0 over the first 20% (20k).
- Neuralangelo: 500k steps; alpha0 0.03 over the first 30% (150k); or a learnable alpha grid
  initialised to 0.03, Adam lr 1e-3 (``--pipeline.model.sp.alpha-grid True``; 128^3 in the
  paper, ``alpha-grid-resolution`` 32 by default here to fit a CPU).
- Hash grid of the paper: 16 levels, resolution 16 to 2048, 2^19 entries, 2 features.

Note that nerfstudio's learning-rate schedulers count absolute steps: for short runs also pass
``--optimizers.fields.scheduler.warm-up-end`` and ``max-steps``.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.plugins.types import MethodSpecification

from sp_plugins.core import SPConfig
from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, alpha_grid_optimizer
from sp_plugins.nerfstudio.components.datamanagers import SurfaceDataManagerConfig
from sp_plugins.nerfstudio.neus import GRID_GROUP, NeuralangeloLiteModelConfig, SPNeuSModelConfig
from sp_plugins.nerfstudio.sdf_field import CoarseToFineSDFFieldConfig
from sp_plugins.nerfstudio.components.schedulers import FloatCosineDecaySchedulerConfig
from sp_plugins.nerfstudio.components.trainer import checked_trainer
from sp_plugins.nerfstudio import table

PAPER_HASH_GRID = dict(num_levels=16, base_res=16, max_res=2048, log2_hashmap_size=19, features_per_level=2)


def _optimizer(lr: float, steps: int, warm_up_end: int) -> dict:
    return {
        "optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
        "scheduler": FloatCosineDecaySchedulerConfig(warm_up_end=warm_up_end, learning_rate_alpha=0.05, max_steps=steps),
    }


def sdf_trainer_config(method_name: str, model, steps: int, lr: float, warm_up_end: int) -> TrainerConfig:
    """A NeuS-style trainer: vanilla (checked) data manager, SDFStudio data by default, and an
    optimizer entry for the SP alpha grid (used only when ``sp.alpha_grid`` is on)."""
    sp: SPConfig = model.sp
    return checked_trainer(
        method_name,
        SurfaceDataManagerConfig(dataparser=SDFStudioDataParserConfig(), train_num_rays_per_batch=1024, eval_num_rays_per_batch=1024),
        model,
        {
            "fields": _optimizer(lr, steps, warm_up_end),
            GRID_GROUP: _optimizer(lr, steps, warm_up_end),  # the hash-grid tables: same settings unless swept
            "field_background": _optimizer(lr, steps, warm_up_end),
            ALPHA_GRID_GROUP: alpha_grid_optimizer(sp, AdamOptimizerConfig),
        },
        viewer_rays=1 << 12,
        steps_per_eval_image=500, steps_per_eval_batch=5000, steps_per_save=20000, steps_per_eval_all_images=1000000,
        max_num_iterations=steps, mixed_precision=False,
    )


def _sp(base: SPConfig, enabled: bool) -> SPConfig:
    return dataclasses.replace(base, enabled=enabled)


def neus_method(name: str, *, hash_grid: bool, sp: bool, description: str) -> MethodSpecification:
    field = CoarseToFineSDFFieldConfig(use_grid_feature=hash_grid, **(PAPER_HASH_GRID if hash_grid else {}))
    if hash_grid:  # a small MLP on the grid, as in nerfstudio's neus-facto
        field = dataclasses.replace(field, num_layers=2, num_layers_color=2, hidden_dim=256)
    model = SPNeuSModelConfig(eval_num_rays_per_chunk=1024, sdf_field=field)
    model.sp = _sp(table.preset_for(model), sp)
    return MethodSpecification(config=sdf_trainer_config(name, model, 100_000, 5e-4, 5000), description=description)


def neuralangelo_method(name: str, *, sp: bool, description: str, alpha_grid: Optional[bool] = None) -> MethodSpecification:
    field = CoarseToFineSDFFieldConfig(
        use_grid_feature=True, numerical_gradients=True, num_layers=2, num_layers_color=2, hidden_dim=256, **PAPER_HASH_GRID
    )
    model = NeuralangeloLiteModelConfig(eval_num_rays_per_chunk=1024, sdf_field=field, coarse_to_fine=not sp)
    model.sp = _sp(table.preset_for(model), sp)
    if alpha_grid is not None:
        model.sp = dataclasses.replace(model.sp, alpha_grid=alpha_grid)
    return MethodSpecification(config=sdf_trainer_config(name, model, 500_000, 1e-3, 5000), description=description)
