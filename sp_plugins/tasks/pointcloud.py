"""Oriented point cloud -> signed distance field (the paper's headline task).

Loss (SIREN, Sitzmann et al. 2020), on B surface points with normals and B uniform points in
the domain box ``[-1, 1]^3``::

    w_surface * mean|f(x_s)| + w_normal * mean(1 - cos(grad f(x_s), n))
    + w_eikonal * mean| |grad f(x)| - 1 | + w_off * mean exp(-falloff * |f(x_o)|)

With stochastic preconditioning every query point is perturbed, ``f(x + alpha * eps)``, and the
gradients are those of the perturbed (blurred) field with respect to ``x``; the targets stay
where they were. After the schedule ends the field is an ordinary field.

The object is first moved into a fixed frame (bounding box centred at 0, diagonal 1.9) so that
every setting (alpha, grid sizes) means the same for every input; meshes are written back in
the input's coordinates and metrics are relative to the ground truth's diagonal.
"""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Literal, Mapping, Optional, Tuple, Type

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from torch import Tensor

from sp_plugins.core import SPConfig
from sp_plugins.geometry import (
    Frame,
    OrientedPoints,
    evaluate_grid,
    largest_component,
    mesh_from_grid,
    mesh_metrics,
)
from sp_plugins.tasks.common import ResumableTrainer, StepTimer, counting_bar, run_to_end, stage
from sp_plugins.tasks.fields import EncodingConfig, NeuralField


def _pointcloud_sp() -> SPConfig:
    # alpha 0.03 (1.6% of the object's diagonal of 1.9; the paper uses about 1%) for the first 20% of
    # training, then exactly 0: the setting of bench/RESULTS.md's point-cloud table.
    return SPConfig(alpha0=0.03, schedule="step", end=0.2)


def _trainer():
    return PointCloudSDFTrainer


@dataclass
class PointCloudSDFConfig:
    """Settings of a point cloud -> SDF fit (``sp-fit pointcloud``)."""

    _target: Type = field(default_factory=_trainer)
    steps: int = 2000
    """Optimisation steps."""
    seed: int = 0
    """Seeds the network initialisation, the batches and (unless sp.seed is set) the SP noise."""
    surface_batch: int = 2500
    """Surface points (with normals) per step."""
    space_batch: int = 2500
    """Uniform points in the domain box per step."""
    n_points: int = 200_000
    """Points sampled from an input mesh (a point-cloud input is used as it is)."""
    lr: float = 1e-3
    """Adam learning rate."""
    lr_final_ratio: float = 1.0
    """The learning rate decays exponentially to lr * this at the last step (1 = constant)."""
    grad_clip: float = 1.0
    """Clip the gradient norm (0 = off)."""
    hidden: Tuple[int, ...] = (64, 64)
    """MLP hidden widths."""
    geometric_init: bool = False
    """Start the MLP as the SDF of a sphere (SAL)."""
    include_input: Optional[bool] = None
    """Feed the coordinates to the MLP next to the encoding's features. None: only with the
    geometric initialisation, which needs them (as the paper's code does)."""
    init_radius: float = 0.5
    """Radius of that sphere, in the frame (the object's diagonal is 1.9)."""
    output_bias: Optional[float] = 0.0
    """Start the MLP's output bias at this value (None: PyTorch's default, uniform in
    +-1/sqrt(width)); ignored with geometric_init, which sets it to -init_radius. Without
    geometric initialisation the sign of the initial output tends to become the sign of the far
    field (see bench/RESULTS.md); 0 leaves that choice to training."""
    w_surface: float = 3e3
    w_normal: float = 1e2
    w_eikonal: float = 5e1
    w_offsurface: float = 1e2
    eikonal: Literal["squared", "abs"] = "squared"
    """Eikonal penalty on (|grad f| - 1): squared (the paper's code) or abs (SIREN's paper)."""
    offsurface_falloff: float = 100.0
    """The off-surface term is exp(-falloff * |f|)."""
    frame_diagonal: float = 1.9
    """Bounding-box diagonal of the object in the [-1, 1]^3 domain."""
    mesh_resolution: int = 192
    """Marching-cubes grid points per axis."""
    refine: int = 4
    """Bisection steps per marching-cubes vertex."""
    metric_points: int = 200_000
    """Samples per mesh for the metrics."""
    fscore_threshold: float = 0.01
    """F-score threshold, as a fraction of the ground truth's diagonal."""
    encoding: EncodingConfig = field(default_factory=EncodingConfig)
    sp: SPConfig = field(default_factory=_pointcloud_sp)

    def validate(self) -> None:
        if self.steps < 1 or self.surface_batch < 1 or self.space_batch < 1 or self.n_points < 1:
            raise ValueError("steps, surface_batch, space_batch and n_points must be >= 1")
        if not (self.lr > 0 and 0 < self.lr_final_ratio <= 1):
            raise ValueError(f"lr={self.lr}, lr_final_ratio={self.lr_final_ratio}: need lr > 0 and 0 < ratio <= 1")
        if self.eikonal not in ("squared", "abs"):
            raise ValueError(f"eikonal={self.eikonal!r}: use 'squared' or 'abs'")
        if self.mesh_resolution < 8:
            raise ValueError(f"mesh_resolution={self.mesh_resolution}: use at least 8")
        self.encoding.validate()
        self.sp.validate()

    def setup(self, data: OrientedPoints, **kwargs) -> "PointCloudSDFTrainer":
        return self._target(self, data, **kwargs)


def siren_sdf_losses(
    f_surface: Float[Tensor, "s"],
    g_surface: Float[Tensor, "s 3"],
    normals: Float[Tensor, "s 3"],
    f_space: Float[Tensor, "o"],
    g_space: Float[Tensor, "o 3"],
    falloff: float = 100.0,
    eikonal: str = "squared",
) -> dict[str, Tensor]:
    """The four unweighted SIREN terms (each a scalar)."""
    grads = torch.cat([g_surface, g_space])
    excess = grads.norm(dim=-1) - 1.0
    return dict(
        surface=f_surface.abs().mean(),
        normal=(1.0 - torch.nn.functional.cosine_similarity(g_surface, normals, dim=-1)).mean(),
        eikonal=(excess.square() if eikonal == "squared" else excess.abs()).mean(),
        offsurface=torch.exp(-falloff * f_space.abs()).mean(),
    )


class PointCloudSDFTrainer(ResumableTrainer):
    """Holds the field, optimiser and data of one fit; :meth:`step` runs one iteration, so
    several trainers can be interleaved step by step in one process (paired benchmarks)."""

    def __init__(self, config: PointCloudSDFConfig, data: OrientedPoints, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config
        self.device = torch.device(device)
        self.frame = Frame.fit(data.points, config.frame_diagonal)
        self.points = torch.as_tensor(self.frame.to_frame(data.points), dtype=torch.float32, device=self.device)
        self.normals = torch.as_tensor(data.normals, dtype=torch.float32, device=self.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            self.field = NeuralField(
                config.encoding,
                dim=3,
                out_dim=1,
                hidden=config.hidden,
                geometric_init=config.geometric_init,
                include_input=config.geometric_init if config.include_input is None else config.include_input,
                init_radius=config.init_radius,
            ).to(self.device)
            if config.output_bias is not None and not config.geometric_init:
                with torch.no_grad():
                    self.field.mlp[-1].bias.fill_(config.output_bias)
        sp_config = config.sp if config.sp.seed is not None else dataclasses.replace(config.sp, seed=config.seed + 1)
        self.sp = sp_config.setup(total_steps=config.steps, bounds=(-1.0, 1.0), dim=3).to(self.device)
        self.sp.train()
        groups = [{"params": list(self.field.parameters()), "lr": config.lr}]
        if self.sp.alpha_grid is not None:
            groups.append({"params": list(self.sp.alpha_grid.parameters()), "lr": sp_config.alpha_grid_lr})
        self.optimizer = torch.optim.Adam(groups)
        gamma = config.lr_final_ratio ** (1.0 / max(config.steps - 1, 1))
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.step_index = 0
        self.history: dict[str, list[float]] = defaultdict(list)
        self.timer = StepTimer(self.device)

    # ------------------------------------------------------------------------------------------
    def step(self) -> Mapping[str, float]:
        """One optimisation step; returns the weighted total and the unweighted terms (read from
        the device when looked at: see :class:`~sp_plugins.tasks.common.ResumableTrainer`)."""
        c = self.config
        with self.timer:
            alpha = self.sp.set_step(self.step_index, c.steps)
            self.field.train()
            idx = torch.randint(len(self.points), (c.surface_batch,), generator=self.generator, device=self.device)
            xo = torch.rand(c.space_batch, 3, generator=self.generator, device=self.device) * 2.0 - 1.0
            x = torch.cat([self.points[idx], xo]).requires_grad_(True)
            f = self.sp.blurred(self.field, x).squeeze(-1)
            (g,) = torch.autograd.grad(f.sum(), x, create_graph=True)
            s = c.surface_batch
            terms = siren_sdf_losses(f[:s], g[:s], self.normals[idx], f[s:], g[s:], c.offsurface_falloff, c.eikonal)
            loss = (
                c.w_surface * terms["surface"]
                + c.w_normal * terms["normal"]
                + c.w_eikonal * terms["eikonal"]
                + c.w_offsurface * terms["offsurface"]
            )
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if c.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(self.field.parameters(), c.grad_clip)
            self.optimizer.step()
            self.scheduler.step()
        # read later, with the non-finite check (no host-device sync per step)
        return self._finish_step({"loss": loss, "alpha": alpha, **terms})

    def _diverged(self, step: int, loss: float) -> str:
        return super()._diverged(step, loss) + " or clip harder (--grad-clip)"

    @property
    def done(self) -> bool:
        return self.step_index >= self.config.steps

    # ------------------------------------------------------------------------------------------
    def sdf(self, x: Float[Tensor, "n 3"]) -> Float[Tensor, "n"]:
        """The plain (unperturbed) field in the frame."""
        self.field.eval()
        return self.field(x).squeeze(-1)

    def mesh(
        self, resolution: Optional[int] = None, refine: Optional[int] = None, progress: bool = False
    ) -> Tuple[trimesh.Trimesh, dict]:
        """Zero level set in the frame, and field diagnostics: ``negative_fraction`` of the grid
        (a sound SDF of an object is mostly positive) and the number of components. ``progress``
        shows what it is doing (it takes a while at high resolutions)."""
        res = resolution or self.config.mesh_resolution
        ref = self.config.refine if refine is None else refine
        with stage(f"meshing: the field on a {res}^3 grid", progress):
            sdf, bar = counting_bar(self.sdf, res**3, "grid points", progress)
            with torch.no_grad():
                volume = evaluate_grid(sdf, (-1.0, 1.0), res, device=self.device)
            bar.close()
        with stage(f"meshing: marching cubes, {ref} bisection steps per vertex", progress):
            mesh = mesh_from_grid(volume, (-1.0, 1.0), self.sdf, refine=ref, device=self.device)
        info = {"negative_fraction": float((volume < 0).mean()), "resolution": res, "refine": ref}
        return mesh, info

    def evaluate(
        self,
        gt_mesh: trimesh.Trimesh,
        *,
        resolution: Optional[int] = None,
        refine: Optional[int] = None,
        metric_points: Optional[int] = None,
        gt_in_frame: bool = False,
        progress: bool = False,
    ) -> Tuple[trimesh.Trimesh, dict]:
        """Mesh (in the frame) and metrics against ``gt_mesh`` (input coordinates unless
        ``gt_in_frame``): raw, and after keeping the largest component (``clean_*``)."""
        c = self.config
        gt = gt_mesh if gt_in_frame else self.frame.mesh_to_frame(gt_mesh)
        mesh, info = self.mesh(resolution, refine, progress)
        n = metric_points or c.metric_points
        with stage(f"measuring: Chamfer, normal consistency and F-score on {n} points per mesh", progress):
            m = mesh_metrics(mesh, gt, n_points=n, fscore_threshold=c.fscore_threshold, seed=c.seed)
        with stage("measuring: the same for the largest component", progress):
            clean = largest_component(mesh)
            mc = mesh_metrics(clean, gt, n_points=n, fscore_threshold=c.fscore_threshold, seed=c.seed)
            components = len(mesh.split(only_watertight=False)) if len(mesh.faces) else 0
        metrics = dict(m, **{f"clean_{k}": v for k, v in mc.items() if k not in ("unit", "n_points", "fscore_threshold")})
        metrics.update(info, components=components, step=self.step_index)
        return mesh, metrics

    def fit(self, callback=None, progress: bool = False) -> None:
        """Run the remaining steps (``callback(trainer, record)`` after each)."""
        run_to_end(self, "sp-fit pointcloud", callback, progress)

