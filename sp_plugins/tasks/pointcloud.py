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

from dataclasses import dataclass, field
from typing import Literal, Mapping, Optional, Tuple, Type, cast

import torch
import trimesh
from jaxtyping import Float
from torch import Tensor

from sp_plugins.core import SPConfig
from sp_plugins.geometry import Frame, OrientedPoints
from sp_plugins.tasks.trainer import SDFTrainer, run_to_end
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.settings import MeshedFitSettings


def _pointcloud_sp() -> SPConfig:
    # alpha 0.03 (1.6% of the object's diagonal of 1.9; the paper uses about 1%) for the first 20% of
    # training, then exactly 0: the setting of the point-cloud table (docs/results/pointcloud-sdf.md).
    return SPConfig(alpha0=0.03, schedule="step", end=0.2)


@dataclass
class PointCloudSDFConfig(MeshedFitSettings):
    """Settings of a point cloud -> SDF fit (``sp-fit pointcloud``)."""

    _target: Type = field(default_factory=lambda: PointCloudSDFTrainer)
    surface_batch: int = 2500
    """Surface points (with normals) per step."""
    space_batch: int = 2500
    """Uniform points in the domain box per step."""
    n_points: int = 200_000
    """Points sampled from an input mesh (a point-cloud input is used as it is)."""
    lr_final_ratio: float = 1.0
    """The learning rate decays exponentially to lr * this at the last step (1 = constant)."""
    grad_clip: float = 1.0
    """Clip the gradient norm (0 = off)."""
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
    field (docs/results/pointcloud-sdf.md); 0 leaves that choice to training."""
    w_surface: float = 3e3
    w_normal: float = 1e2
    w_eikonal: float = 5e1
    w_offsurface: float = 1e2
    eikonal: Literal["squared", "abs"] = "squared"
    """Eikonal penalty on ``|grad f| - 1``: squared (the paper's code) or abs (SIREN's paper)."""
    offsurface_falloff: float = 100.0
    """The off-surface term is ``exp(-falloff * |f|)``."""
    encoding: EncodingConfig = field(default_factory=EncodingConfig)
    sp: SPConfig = field(default_factory=_pointcloud_sp)

    def validate(self) -> None:
        if self.steps < 1 or self.surface_batch < 1 or self.space_batch < 1 or self.n_points < 1:
            raise ValueError("steps, surface_batch, space_batch and n_points must be >= 1")
        if not (self.lr > 0 and 0 < self.lr_final_ratio <= 1):
            raise ValueError(f"lr={self.lr}, lr_final_ratio={self.lr_final_ratio}: need lr > 0 and 0 < ratio <= 1")
        if not self.grad_clip >= 0:  # clip_grad_norm_ with a negative bound flips the gradient's sign
            raise ValueError(f"grad_clip={self.grad_clip}: use 0 (off) or a positive gradient norm")
        check_eikonal(self.eikonal)
        self.validate_meshing()
        self.encoding.validate()
        self.sp.validate()

    def setup(self, data: OrientedPoints, **kwargs) -> "PointCloudSDFTrainer":
        return self._target(self, data, **kwargs)


def check_eikonal(name: str) -> None:
    """The eikonal penalty is named "squared" or "abs"; anything else is refused in one line."""
    if name not in ("squared", "abs"):
        raise ValueError(f"eikonal={name!r}: use 'squared' or 'abs'")


def siren_sdf_losses(
    f_surface: Float[Tensor, " s"],
    g_surface: Float[Tensor, "s 3"],
    normals: Float[Tensor, "s 3"],
    f_space: Float[Tensor, " o"],
    g_space: Float[Tensor, "o 3"],
    falloff: float = 100.0,
    eikonal: Literal["squared", "abs"] = "squared",
) -> dict[str, Tensor]:
    """The four unweighted SIREN terms (each a scalar). ``eikonal``: the penalty on ``|grad f| - 1``,
    squared or absolute; any other name is refused (a library call is not validated by a config)."""
    check_eikonal(eikonal)
    grads = torch.cat([g_surface, g_space])
    excess = grads.norm(dim=-1) - 1.0
    return dict(
        surface=f_surface.abs().mean(),
        normal=(1.0 - torch.nn.functional.cosine_similarity(g_surface, normals, dim=-1)).mean(),
        eikonal=(excess.square() if eikonal == "squared" else excess.abs()).mean(),
        offsurface=torch.exp(-falloff * f_space.abs()).mean(),
    )


class PointCloudSDFTrainer(SDFTrainer):
    """Holds the field, optimiser and data of one fit; :meth:`step` runs one iteration, so
    several trainers can be interleaved step by step in one process (paired benchmarks)."""

    def __init__(self, config: PointCloudSDFConfig, data: OrientedPoints, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config
        self.device = torch.device(device)
        self.frame = Frame.fit(data.points, config.frame_diagonal)
        self.points = torch.as_tensor(self.frame.to_frame(data.points), dtype=torch.float32, device=self.device)
        self.normals = torch.as_tensor(data.normals, dtype=torch.float32, device=self.device)
        self.field = self._build_field(
            dim=3,
            out_dim=1,
            hidden=config.hidden,
            geometric_init=config.geometric_init,
            include_input=config.geometric_init if config.include_input is None else config.include_input,
            init_radius=config.init_radius,
        )
        if config.output_bias is not None and not config.geometric_init:
            with torch.no_grad():
                cast(torch.nn.Linear, self.field.mlp[-1]).bias.fill_(config.output_bias)
        sp_config = self._setup_sp(bounds=(-1.0, 1.0), dim=3)
        self.optimizer = torch.optim.Adam(self._param_groups(sp_config))
        gamma = config.lr_final_ratio ** (1.0 / max(config.steps - 1, 1))
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma)
        self._start_steps()

    # ------------------------------------------------------------------------------------------
    def step(self) -> Mapping[str, float]:
        """One optimisation step; returns the weighted total and the unweighted terms (read from
        the device when looked at: see :class:`~sp_plugins.tasks.trainer.ResumableTrainer`)."""
        c = self.config
        with self.timer:
            alpha = self.sp.step_pre(self.step_index)
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
            self.sp.step_post(self.step_index)
        # read later, with the non-finite check (no host-device sync per step)
        return self._finish_step({"loss": loss, "alpha": alpha, **terms})

    def _diverged(self, step: int, loss: float) -> str:
        return super()._diverged(step, loss) + " or clip harder (--grad-clip)"

    # sdf(), mesh() and mesh_metrics(): SDFTrainer's
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
        gt = gt_mesh if gt_in_frame else self.frame.mesh_to_frame(gt_mesh)
        mesh, info = self.mesh(resolution, refine, progress)
        metrics = self.mesh_metrics(mesh, gt, metric_points, progress)
        components = len(mesh.split(only_watertight=False)) if len(mesh.faces) else 0
        metrics.update(info, components=components, step=self.step_index)
        return mesh, metrics

    def fit(self, callback=None, progress: bool = False) -> None:
        """Run the remaining steps (``callback(trainer, record)`` after each)."""
        run_to_end(self, "sp-fit pointcloud", callback, progress)

