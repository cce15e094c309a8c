"""Trainer configs of the radiance methods (:mod:`sp_plugins.method_configs.nerfstudio` only picks one each).

- ReLU fields (paper: 256^3 grid, Adam lr 0.03, alpha0 0.003 over the first 8000 steps; 28k steps
  of 16k rays x 512 samples): ``relu-field`` (4-stage coarse-to-fine), ``relu-field-flat`` and
  ``sp-relu-field``. The grid here has 257 vertices per axis so every upsampling is exact.
- ``sp-mipnerf``: nerfstudio's mipnerf settings (RAdam 5e-4, 1024 rays, 128 + 128 samples) with
  SP on the Gaussian means (alpha0 0.04, exponential to 0 by step 2500 of the preset's 7500,
  a third of training when a run is shortened). With sparse views that preset changes nothing;
  alpha0 about the object's radius (``--pipeline.model.sp.alpha0 1.0`` on the DTU-like scenes)
  helps only where MipNeRF fails (held-out views of fog) and harms where it does not (a white
  background): the figures are in ``docs/results/sparse-views.md``,
  guarded by the opt-in ``tests/bench/test_sparse_views_gap.py`` (``SP_SLOW_TESTS=1``).
- ``sp-vanilla-nerf``, ``sp-nerfacto``, ``sp-tensorf``: nerfstudio's settings for each host, made
  SP methods by the generic route (``with_sp``) with their presets (``sp-nerfacto`` on
  :class:`~sp_plugins.nerfstudio.components.hash_encoding.NerfactoHashGridModel`, our hash grids where tcnn
  cannot run; ``sp-tensorf`` reflecting inside the scene box).

All use the checked vanilla data manager (no worker processes), which also takes
``--pipeline.datamanager.train-views N`` for the sparse-view setting.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig, RAdamOptimizerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.tensorf import TensoRFModelConfig
from nerfstudio.models.vanilla_nerf import NeRFModel, VanillaModelConfig
from nerfstudio.plugins.types import MethodSpecification

from sp_plugins.adapter import presets
from sp_plugins.nerfstudio import table
from sp_plugins.adapter.callbacks import ALPHA_GRID_GROUP, alpha_grid_optimizer
from sp_plugins.nerfstudio.components.datamanagers import CheckedDataManagerConfig
from sp_plugins.nerfstudio.components.hash_encoding import NerfactoHashGridModelConfig
from sp_plugins.nerfstudio.mipnerf import SPMipNerfModelConfig
from sp_plugins.nerfstudio.relu_field.model import ReLUFieldModelConfig
from sp_plugins.nerfstudio.components.schedulers import FloatExponentialDecaySchedulerConfig
from sp_plugins.nerfstudio.components.trainer import checked_trainer
from sp_plugins.nerfstudio.registration import with_sp


@dataclass
class FusedAdamOptimizerConfig(AdamOptimizerConfig):
    """Adam with the fused kernel (torch >= 2.4, CPU and CUDA): on a dense grid the optimizer step
    is several times faster than the default foreach kernel on a CPU."""

    fused: Optional[bool] = True
    """torch.optim.Adam's fused implementation; None lets torch choose."""


MIPNERF_STEPS = 7_500
"""sp-mipnerf's preset length: SP ends at the paper's step 2500, a third of training (the paper's
"by 1/3 of training at the latest"); nerfstudio's own mipnerf preset has no length (1M steps)."""


def _with_sp_optimizer(config: TrainerConfig, description: str) -> MethodSpecification:
    """The method spec, with the optimizer entry a learnable alpha grid needs."""
    config.optimizers[ALPHA_GRID_GROUP] = alpha_grid_optimizer(config.pipeline.model.sp, AdamOptimizerConfig)
    return MethodSpecification(config=config, description=description)


def relu_field_method(name: str, *, stages: int, sp: bool, description: str) -> MethodSpecification:
    model = ReLUFieldModelConfig(
        resolution=257,
        hierarchy_stages=stages,
        num_samples=512,
        eval_num_rays_per_chunk=4096,
    )
    model.sp = dataclasses.replace(table.preset_for(model), enabled=sp)
    config = checked_trainer(
        name,
        CheckedDataManagerConfig(dataparser=BlenderDataParserConfig(), train_num_rays_per_batch=16384, eval_num_rays_per_batch=4096),
        model,
        {"fields": {"optimizer": FusedAdamOptimizerConfig(lr=0.03, eps=1e-15), "scheduler": None}},
        viewer_rays=1 << 14,
        steps_per_eval_batch=500, steps_per_eval_image=500, steps_per_save=2000, max_num_iterations=presets.RELU_FIELD_STEPS,
        mixed_precision=False,
    )
    return _with_sp_optimizer(config, description)


def mipnerf_method(name: str, *, sp: bool, description: str) -> MethodSpecification:
    model = SPMipNerfModelConfig(
        loss_coefficients={"rgb_loss_coarse": 0.1, "rgb_loss_fine": 1.0},
        num_coarse_samples=128,
        num_importance_samples=128,
        eval_num_rays_per_chunk=1024,
    )
    model.sp = dataclasses.replace(table.preset_for(model), enabled=sp)
    config = checked_trainer(
        name,
        CheckedDataManagerConfig(dataparser=BlenderDataParserConfig(), train_num_rays_per_batch=1024),
        model,
        {"fields": {"optimizer": RAdamOptimizerConfig(lr=5e-4, eps=1e-08), "scheduler": None}},
        max_num_iterations=MIPNERF_STEPS,
    )
    return _with_sp_optimizer(config, description)


def _decaying_adam(lr: float, lr_final: float, max_steps: int, **adam: float) -> dict:
    """An optimizer group of nerfstudio's presets: Adam at ``lr``, decaying exponentially to ``lr_final``
    over ``max_steps`` (``adam``: the optimizer's other settings, e.g. ``eps``)."""
    return {
        "optimizer": AdamOptimizerConfig(lr=lr, **adam),
        "scheduler": FloatExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=max_steps),
    }


HOST_SCHEDULE = dict(viewer_rays=1 << 15, steps_per_eval_batch=500, steps_per_save=2000, max_num_iterations=30000)
"""nerfstudio's own schedule of nerfacto and tensorf (30k steps), which their SP methods keep."""


def _generic(config: TrainerConfig, description: str) -> MethodSpecification:
    """A host method plus SP: the generic route (``with_sp``), with the preset ``sp-train`` gives it
    (:func:`sp_plugins.nerfstudio.table.preset_for`)."""
    return with_sp(config, name=config.method_name, description=description)


def vanilla_nerf_method(name: str, description: str) -> MethodSpecification:
    config = checked_trainer(
        name,
        CheckedDataManagerConfig(dataparser=BlenderDataParserConfig()),
        VanillaModelConfig(_target=NeRFModel),
        {
            "fields": {"optimizer": RAdamOptimizerConfig(lr=5e-4, eps=1e-08), "scheduler": None},
            "temporal_distortion": {"optimizer": RAdamOptimizerConfig(lr=5e-4, eps=1e-08), "scheduler": None},
        },
    )
    return _generic(config, description)


def nerfacto_method(name: str, description: str) -> MethodSpecification:
    decay = FloatExponentialDecaySchedulerConfig(lr_final=0.0001, max_steps=200000)
    config = checked_trainer(
        name,
        CheckedDataManagerConfig(dataparser=NerfstudioDataParserConfig(), train_num_rays_per_batch=4096, eval_num_rays_per_batch=4096),
        NerfactoHashGridModelConfig(
            eval_num_rays_per_chunk=1 << 15, average_init_density=0.01, camera_optimizer=CameraOptimizerConfig(mode="SO3xR3")
        ),
        {
            "proposal_networks": {"optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15), "scheduler": decay},
            "fields": {"optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15), "scheduler": decay},
            "camera_opt": _decaying_adam(1e-3, 1e-4, 5000, eps=1e-15),
        },
        **HOST_SCHEDULE, mixed_precision=True,
    )
    return _generic(config, description)


def tensorf_method(name: str, description: str) -> MethodSpecification:
    config = checked_trainer(
        name,
        CheckedDataManagerConfig(dataparser=BlenderDataParserConfig(), train_num_rays_per_batch=4096, eval_num_rays_per_batch=4096),
        TensoRFModelConfig(regularization="tv", camera_optimizer=CameraOptimizerConfig(mode="off")),
        {
            "fields": _decaying_adam(0.001, 0.0001, 30000),
            "encodings": _decaying_adam(0.02, 0.002, 30000),
            "camera_opt": _decaying_adam(1e-4, 1e-5, 5000, eps=1e-15),
        },
        **HOST_SCHEDULE, mixed_precision=False,
    )
    return _generic(config, description)
