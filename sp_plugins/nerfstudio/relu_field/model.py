"""ReLU-field models: the original coarse-to-fine hierarchy, flat training, and flat + SP.

One model class covers the three methods:

- ``hierarchy_stages=4`` (``relu-field``): training is split into equal stages; the grid starts at
  ``(resolution - 1) / 8 + 1`` vertices per axis and is upsampled (exact trilinear resampling)
  at the start of each stage, with the optimizer state of the grid reset;
- ``hierarchy_stages=1`` (``relu-field-flat``): full resolution from step 0;
- flat with ``sp.enabled`` (``sp-relu-field``): full resolution, positions perturbed while training.

Rendering: stratified uniform samples between the ray's entry into and exit from the scene box,
alpha compositing onto a white background, MSE on colour.

Against the original (thr3ed_atom, Karnewar et al.), configurable here and used by the
paper-regime study (``bench/radiance_methods.py relu --paper-regime``); the presets keep our defaults:

- grid layout: ``align_corners=False`` is thr3ed_atom's cell-centred grid (``resolution`` cells,
  zero padding, 32 -> 256 cells); our default is a vertex grid (2^k + 1 vertices) because its
  upsampling is exact, where the cell grid's smooths the field slightly and clamps at the walls.
- density: ``density_units="world"`` with ``density_scale=100/3`` is thr3ed_atom's raw values
  U[-1, 1] times 100/3 per world unit for a 3-unit grid; our default scales by 1/voxel of the full
  grid (an optical depth of ``density_scale`` per voxel, the same at every resolution).
- loss: ``loss="l1"`` plus ``diffuse_loss_weight=1`` (an L1 loss on the SH degree-0 render, needs
  ``sh`` colour) is thr3ed_atom's; our default is MSE.
- learning rate: reset per stage with x0.1 steps inside it is
  :class:`~sp_plugins.nerfstudio.relu_field.lr.StagedStepDecaySchedulerConfig`; the Adam moments are
  reset per stage in both (``reset_optimizer_per_stage``).

Differences we keep: the grid spans the scene box, which for Blender data is thr3ed_atom's
[-1.5, 1.5]^3 already; samples are stratified between the ray's box entry and exit rather than over
the camera bounds (outside the box the density is zero, so only the spacing matters: choose
``num_samples`` for it); rays are drawn from all training images rather than 8 cached ones, and
images are not downsampled per stage (coarse stages see more pixels per voxel, not fewer); SH
degree 2 is available (``sh_degree=2``) but costs about 7x the RGB step on a CPU.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.losses import L1Loss, MSELoss
from nerfstudio.model_components.ray_samplers import UniformSampler
from nerfstudio.model_components.renderers import AccumulationRenderer, DepthRenderer, RGBRenderer
from nerfstudio.model_components.scene_colliders import AABBBoxCollider
from nerfstudio.models.base_model import Model, ModelConfig
from nerfstudio.utils import colormaps
from torch.nn import Parameter

from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio.model import SPModel, SPModelConfig
from sp_plugins.nerfstudio.relu_field.field import DIFFUSE_RGB, ColorMode, ReLUField, color_channels, upsample_grid
from sp_plugins.nerfstudio.relu_field.lr import StagedStepDecaySchedulerConfig, stage_at

log = logging.getLogger(__name__)

GRID_GROUP = "fields"
"""Optimizer group holding the grid."""


def voxel_size(aabb: torch.Tensor, resolution: int, align_corners: bool = True) -> float:
    """Edge of one voxel of a grid with ``resolution`` vertices (``align_corners``) or cells per axis
    spanning ``aabb`` ``[2, 3]`` (along its longest side): the unit of ``density_scale`` (in voxel
    units), and a natural unit for SP's alpha."""
    return float((aabb[1] - aabb[0]).max()) / (resolution - 1 if align_corners else resolution)


def stage_resolutions(resolution: int, stages: int, align_corners: bool = True) -> List[int]:
    """Values per axis of each stage, coarsest first, halving the cell count per stage:
    129 vertices over 4 stages gives 17, 33, 65, 129; 64 cells (``align_corners=False``) 8, 16, 32, 64."""
    if stages < 1:
        raise ValueError(f"hierarchy_stages={stages}: must be >= 1 (1 = flat training)")
    if not align_corners:
        step = 2 ** (stages - 1)
        if resolution < step or resolution % step:
            raise ValueError(
                f"resolution={resolution} cells cannot be halved {stages - 1} times: use a multiple of {step} "
                "or fewer stages"
            )
        return [resolution // 2 ** (stages - 1 - k) for k in range(stages)]
    cells = resolution - 1
    out = [max(1, round(cells / 2 ** (stages - 1 - k))) + 1 for k in range(stages)]
    if min(out) < 2 or len(set(out)) != stages:
        raise ValueError(
            f"resolution={resolution} is too coarse for {stages} stages: each stage halves the cells per axis; "
            f"use resolution >= {2 ** (stages - 1) + 1} or fewer stages"
        )
    return out


def swap_parameter(optimizers: Optimizers, group: str, old: Parameter, new: Parameter, reset: bool,
                   align_corners: bool = True) -> None:
    """Make ``optimizers[group]`` optimize ``new`` instead of ``old``: its Adam moments are dropped
    (``reset``) or resampled onto ``new``'s grid."""
    optimizer = optimizers.optimizers[group]
    for param_group in optimizer.param_groups:
        param_group["params"] = [new if p is old else p for p in param_group["params"]]
    optimizers.parameters[group] = [new if p is old else p for p in optimizers.parameters[group]]
    state = optimizer.state.pop(old, None)
    if state and not reset:
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                state[key] = upsample_grid(state[key], new.shape[-1], align_corners).contiguous()
        optimizer.state[new] = state


@dataclass
class ReLUFieldModelConfig(SPModelConfig, ModelConfig):
    """A dense ReLU field rendered by stratified sampling inside the scene box."""

    _target: Type = field(default_factory=lambda: ReLUFieldModel)
    enable_collider: bool = False
    """Unused: rays are always clipped to the scene box (an AABB collider)."""
    resolution: int = 129
    """Vertices (cells with --pipeline.model.align-corners False) per axis of the full-resolution
    grid; 2^k + 1 vertices make every upsampling exact."""
    align_corners: bool = True
    """True: a vertex grid, the first and last vertices on the box faces; False: thr3ed_atom's grid
    of cells with values at their centres, fading to zero across the outer half cells."""
    hierarchy_stages: int = 1
    """Coarse-to-fine stages of equal length; 1 trains at full resolution from step 0."""
    reset_optimizer_per_stage: bool = True
    """Clear the grid's Adam moments when a stage upsamples it (the original scheme)."""
    color_mode: ColorMode = "sh"
    """sh: view-dependent colour from spherical harmonics; rgb: one colour per point."""
    sh_degree: int = 1
    """Degree of the spherical harmonics (0-3) for color_mode sh."""
    density_scale: float = 1.0
    """Density = relu(raw) * density_scale / voxel, the voxel of the full-resolution grid: a raw
    value of 1 is an optical depth of density_scale across one voxel at every resolution
    (density_units voxel); or relu(raw) * density_scale per world unit (density_units world)."""
    density_units: Literal["voxel", "world"] = "voxel"
    """Unit of density_scale: per voxel of the full grid, or per world unit (thr3ed_atom: 100/3)."""
    loss: Literal["mse", "l1"] = "mse"
    """Colour loss: MSE, or L1 (thr3ed_atom)."""
    diffuse_loss_weight: float = 0.0
    """Weight of thr3ed_atom's extra loss (same kind as loss) on the diffuse render, the SH degree-0
    colour composited with the same weights; needs color_mode sh. 0 turns it off."""
    density_init: Tuple[float, float] = (-1.0, 1.0)
    """Uniform range of the initial raw density values."""
    color_init: Tuple[float, float] = (-1.0, 1.0)
    """Uniform range of the initial raw colour values (before the sigmoid)."""
    num_samples: int = 96
    """Stratified samples per ray inside the box."""
    background_color: Literal["white", "black", "random"] = "white"
    """Colour behind the field; random (a new colour per ray while training) needs RGBA images
    (Blender data: --alpha-color None) and keeps floaters from hiding in front of a white background."""

    def __post_init__(self) -> None:
        color_channels(self.color_mode, self.sh_degree)
        stage_resolutions(self.resolution, self.hierarchy_stages, self.align_corners)
        if not self.diffuse_loss_weight >= 0:
            raise ValueError(f"diffuse_loss_weight={self.diffuse_loss_weight}: must be >= 0")
        if self.num_samples < 1:
            raise ValueError(f"num_samples={self.num_samples}: must be >= 1")


class ReLUFieldBaseModel(Model):
    """The ReLU-field renderer and its coarse-to-fine hierarchy (no SP of its own)."""

    config: ReLUFieldModelConfig
    field: ReLUField

    def populate_modules(self) -> None:
        super().populate_modules()
        c = self.config
        if c.diffuse_loss_weight > 0 and c.color_mode != "sh":
            raise InputError(
                f"--pipeline.model.diffuse-loss-weight {c.diffuse_loss_weight:g} needs --pipeline.model.color-mode sh "
                "(the diffuse render is the SH degree-0 colour; with rgb it would be the render itself): "
                "pass --pipeline.model.color-mode sh or --pipeline.model.diffuse-loss-weight 0"
            )
        self.resolutions = stage_resolutions(c.resolution, c.hierarchy_stages, c.align_corners)
        aabb = self.scene_box.aabb.float()
        voxel = voxel_size(aabb, c.resolution, c.align_corners)
        self.field = ReLUField(
            aabb,
            self.resolutions[0],
            color_mode=c.color_mode,
            sh_degree=c.sh_degree,
            density_scale=c.density_scale / voxel if c.density_units == "voxel" else c.density_scale,
            density_init=c.density_init,
            color_init=c.color_init,
            align_corners=c.align_corners,
            diffuse_output=c.diffuse_loss_weight > 0,
        )
        self.collider = AABBBoxCollider(self.scene_box)
        self.sampler = UniformSampler(num_samples=c.num_samples, train_stratified=True)
        self.renderer_rgb = RGBRenderer(background_color=c.background_color)
        self.renderer_accumulation = AccumulationRenderer()
        self.renderer_depth = DepthRenderer(method="expected")
        self.rgb_loss = MSELoss() if c.loss == "mse" else L1Loss()

        from torchmetrics.functional import structural_similarity_index_measure
        from torchmetrics.image import PeakSignalNoiseRatio
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = structural_similarity_index_measure
        self.lpips = LearnedPerceptualImagePatchSimilarity(normalize=True)

    # -- hierarchy ---------------------------------------------------------------------------
    def stage_for_step(self, step: int, total_steps: int) -> int:
        return stage_at(step, total_steps, self.config.hierarchy_stages)

    def set_stage(self, stage: int, optimizers: Optional[Optimizers] = None) -> bool:
        """Upsample the grid to ``stage``'s resolution (never down); reset its optimizer state.
        Returns whether the resolution changed."""
        target = self.resolutions[stage]
        if target <= self.field.resolution:
            return False
        log.info("relu-field: grid %d^3 -> %d^3 (stage %d)", self.field.resolution, target, stage)
        old = self.field.grid
        new = self.field.upsample_to(target)
        if optimizers is not None and GRID_GROUP in optimizers.optimizers:
            swap_parameter(optimizers, GRID_GROUP, old, new, reset=self.config.reset_optimizer_per_stage,
                           align_corners=self.config.align_corners)
        return True

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = list(super().get_training_callbacks(training_callback_attributes))
        total = self.sp_run_length(training_callback_attributes).total
        world_size = int(getattr(training_callback_attributes.trainer, "world_size", 1) or 1)
        if self.config.hierarchy_stages > 1 and world_size > 1:
            # each stage swaps the grid for a new Parameter, which DDP's gradient all-reduce never sees
            raise InputError(
                f"--pipeline.model.hierarchy-stages {self.config.hierarchy_stages} cannot train on {world_size} devices "
                "(each stage replaces the grid parameter, which DistributedDataParallel would not synchronise); "
                "train the hierarchy on one device (--machine.num-devices 1) or use relu-field-flat / sp-relu-field"
            )
        self._check_staged_schedule(training_callback_attributes, total)
        if self.config.hierarchy_stages > 1 and total is not None:
            optimizers = training_callback_attributes.optimizers

            def to_stage(step: int) -> None:
                self.set_stage(self.stage_for_step(step, total), optimizers)

            callbacks.append(
                TrainingCallback(
                    where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], func=to_stage, update_every_num_iters=1
                )
            )
        return callbacks

    def _check_staged_schedule(self, attributes: TrainingCallbackAttributes, total: Optional[int]) -> None:
        """A per-stage learning-rate schedule must restart where this model upsamples."""
        trainer_config = getattr(getattr(attributes, "trainer", None), "config", None)
        group = getattr(trainer_config, "optimizers", {}).get(GRID_GROUP, {}) if trainer_config is not None else {}
        scheduler = group.get("scheduler") if isinstance(group, dict) else None
        if not isinstance(scheduler, StagedStepDecaySchedulerConfig):
            return
        stages = self.config.hierarchy_stages
        if scheduler.stages != stages or (total is not None and scheduler.max_steps != total):
            raise InputError(
                f"--optimizers.fields.scheduler.stages {scheduler.stages} / .max-steps {scheduler.max_steps} do not match "
                f"--pipeline.model.hierarchy-stages {stages} / --max-num-iterations {total}: the learning rate would "
                "restart away from the grid's upsampling; give the scheduler the same stages and steps"
            )

    # -- rendering ---------------------------------------------------------------------------
    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return {GRID_GROUP: [self.field.grid]}

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, torch.Tensor]:
        ray_samples = self.sampler(ray_bundle)
        field_outputs = self.field(ray_samples)
        weights = ray_samples.get_weights(field_outputs[FieldHeadNames.DENSITY])
        outputs = {
            "rgb": self.renderer_rgb(rgb=field_outputs[FieldHeadNames.RGB], weights=weights),
            "accumulation": self.renderer_accumulation(weights),
            "depth": self.renderer_depth(weights, ray_samples),
        }
        if DIFFUSE_RGB in field_outputs:
            outputs[DIFFUSE_RGB] = self.renderer_rgb(rgb=field_outputs[DIFFUSE_RGB], weights=weights)
        return outputs

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        image = batch["image"].to(self.device)
        if self.config.background_color == "random" and image.shape[-1] != 4:
            raise ValueError(
                "background_color='random' needs images with an alpha channel, but the data manager serves RGB "
                "(already composited): for Blender data pass `blender-data --alpha-color None`"
            )
        pred, gt = self.renderer_rgb.blend_background_for_loss_computation(
            pred_image=outputs["rgb"], pred_accumulation=outputs["accumulation"], gt_image=image
        )
        losses = {"rgb_loss": self.rgb_loss(gt, pred)}
        if DIFFUSE_RGB in outputs and self.training:
            diffuse, gt = self.renderer_rgb.blend_background_for_loss_computation(
                pred_image=outputs[DIFFUSE_RGB], pred_accumulation=outputs["accumulation"], gt_image=image
            )
            losses["diffuse_rgb_loss"] = self.config.diffuse_loss_weight * self.rgb_loss(gt, diffuse)
        return losses

    def get_metrics_dict(self, outputs, batch) -> Dict[str, torch.Tensor]:
        gt = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        return {"psnr": self.psnr(outputs["rgb"], gt), "grid_resolution": self.field.resolution}

    def get_image_metrics_and_images(self, outputs, batch):
        gt = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        rgb = outputs["rgb"]
        acc = colormaps.apply_colormap(outputs["accumulation"])
        depth = colormaps.apply_depth_colormap(outputs["depth"], accumulation=outputs["accumulation"])
        gt_, rgb_ = (torch.moveaxis(t, -1, 0)[None] for t in (gt, rgb.clamp(0, 1)))
        metrics = {
            "psnr": float(self.psnr(gt_, rgb_).item()),
            "ssim": float(self.ssim(gt_, rgb_)),  # type: ignore[arg-type]
            "lpips": float(self.lpips(gt_, rgb_)),
        }
        images = {"img": torch.cat([gt, rgb], dim=1), "accumulation": acc, "depth": depth}
        return metrics, images


class ReLUFieldModel(SPModel, ReLUFieldBaseModel):
    """ReLU field with the shared SP settings (``sp.enabled=False`` for the baselines)."""

    config: ReLUFieldModelConfig

