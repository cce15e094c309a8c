"""Direct SDF fitting from a mesh's signed distance (the Instant-NGP SDF task).

A fixed pool of samples is drawn once, 50% on the surface (distance 0), 25% near it (surface
points moved by N(0, near_sigma^2) per axis) and 25% uniform in the domain box, with their
signed distances (exact closest points from trimesh; the sign from ray-based containment for
watertight meshes, else from the closest face's normal). Each step takes a batch with the same
mix and minimises the mean absolute percentage error ``|f - d| / (|d| + 0.01)``. SP queries
``f(x + alpha * eps)`` against ``d(x)``. Runs in the same frame as the point-cloud task.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Optional, Tuple, Type

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from torch import Tensor

from sp_plugins.core import SPConfig
from sp_plugins.geometry import Frame, sample_surface
from sp_plugins.tasks.trainer import SDFTrainer, run_to_end
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.settings import MeshedFitSettings


def _sdf_sp() -> SPConfig:
    return SPConfig(alpha0=0.02, schedule="step", end=0.2)


@dataclass
class SDFFitConfig(MeshedFitSettings):
    """Settings of a direct SDF fit (``sp-fit sdf``)."""

    _target: Type = field(default_factory=lambda: SDFFitTrainer)
    batch: int = 8192
    """Samples per step (50% surface, 25% near, 25% uniform)."""
    pool: int = 100_000
    """Samples with precomputed distances drawn once before training."""
    near_sigma: float = 0.02
    """Standard deviation of the near-surface offsets, in the frame (diagonal 1.9)."""
    encoding: EncodingConfig = field(default_factory=EncodingConfig)
    sp: SPConfig = field(default_factory=_sdf_sp)

    def validate(self) -> None:
        if self.steps < 1 or self.batch < 4 or self.pool < 8 or self.lr <= 0 or self.near_sigma <= 0:
            raise ValueError("steps >= 1, batch >= 4, pool >= 8, lr > 0 and near_sigma > 0 are required")
        self.validate_meshing()
        self.encoding.validate()
        self.sp.validate()

    def setup(self, mesh: trimesh.Trimesh, **kwargs) -> "SDFFitTrainer":
        return self._target(self, mesh, **kwargs)


def signed_distance(
    mesh: trimesh.Trimesh, points: Float[np.ndarray, "n 3"], chunk: int = 8192
) -> Float[np.ndarray, " n"]:
    """Signed distance to ``mesh`` (negative inside), ``chunk`` points at a time (trimesh's
    closest-point query holds large candidate arrays)."""
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk]
        closest, dist, tri = trimesh.proximity.closest_point(mesh, p)
        if mesh.is_watertight:
            inside = mesh.contains(p)
        else:
            inside = np.sum((p - closest) * mesh.face_normals[tri], axis=1) < 0
        out[s : s + chunk] = np.where(inside, -dist, dist)
    return out


def mape(pred: Tensor, target: Tensor, eps: float = 0.01) -> Tensor:
    """Instant-NGP's mean absolute percentage error."""
    return ((pred - target).abs() / (target.abs() + eps)).mean()


class SDFFitTrainer(SDFTrainer):
    """One direct SDF fit; :meth:`step` runs one iteration."""

    def __init__(self, config: SDFFitConfig, mesh: trimesh.Trimesh, *, device: str = "cpu") -> None:
        config.validate()
        if len(mesh.faces) == 0:
            raise ValueError("sdf fitting needs a mesh with faces")
        self.config = config
        self.device = torch.device(device)
        self.frame = Frame.fit(np.asarray(mesh.vertices), config.frame_diagonal)
        self.mesh_in_frame = self.frame.mesh_to_frame(mesh)
        rng = np.random.default_rng(config.seed)
        n_surface = config.pool // 2
        n_near = config.pool // 4
        n_uniform = config.pool - n_surface - n_near
        surface, _ = sample_surface(self.mesh_in_frame, n_surface + n_near, seed=config.seed)
        near = surface[n_surface:] + rng.normal(0.0, config.near_sigma, (n_near, 3))
        uniform = rng.uniform(-1.0, 1.0, (n_uniform, 3))
        queries = np.concatenate([near, uniform])
        dists = signed_distance(self.mesh_in_frame, queries)
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=self.device)  # noqa: E731
        self.groups = [
            (as_t(surface[:n_surface]), torch.zeros(n_surface, device=self.device)),
            (as_t(near), as_t(dists[:n_near])),
            (as_t(uniform), as_t(dists[n_near:])),
        ]
        self.field = self._build_field(dim=3, out_dim=1, hidden=config.hidden, include_input=False)
        sp_config = self._setup_sp(bounds=(-1.0, 1.0), dim=3)
        self.optimizer = torch.optim.Adam(self._param_groups(sp_config), betas=(0.9, 0.99), eps=1e-15)
        self._start_steps()

    def step(self) -> Mapping[str, float]:
        c = self.config
        with self.timer:
            alpha = self.sp.step_pre(self.step_index)
            sizes = (c.batch // 2, c.batch // 4, c.batch - c.batch // 2 - c.batch // 4)
            xs, ds = [], []
            for (pts, dist), k in zip(self.groups, sizes):
                idx = torch.randint(len(pts), (k,), generator=self.generator, device=self.device)
                xs.append(pts[idx])
                ds.append(dist[idx])
            x, d = torch.cat(xs), torch.cat(ds)
            pred = self.sp.blurred(self.field, x).squeeze(-1)
            loss = mape(pred, d)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            self.sp.step_post(self.step_index)
        return self._finish_step({"loss": loss, "alpha": alpha})  # read later, with the non-finite check

    def evaluate(self, gt_mesh: Optional[trimesh.Trimesh] = None, *, resolution: Optional[int] = None,
                 metric_points: Optional[int] = None, progress: bool = False) -> Tuple[trimesh.Trimesh, dict]:
        """Mesh in the frame and metrics against the (input) mesh, raw and ``clean_*``; ``progress``
        says what it is doing."""
        gt = self.mesh_in_frame if gt_mesh is None else self.frame.mesh_to_frame(gt_mesh)
        mesh, info = self.mesh(resolution, progress=progress)
        metrics = self.mesh_metrics(mesh, gt, metric_points, progress)
        metrics.update(info, step=self.step_index)
        # Also how well the field fits distances on held-in samples near the surface.
        with torch.no_grad():
            pts, dist = self.groups[1]
            metrics["near_mae"] = float((self.sdf(pts[:20000]) - dist[:20000]).abs().mean())
        self.field.train()
        return mesh, metrics

    def fit(self, callback=None, progress: bool = False) -> None:
        """Run the remaining steps (``callback(trainer, record)`` after each)."""
        run_to_end(self, "sp-fit sdf", callback, progress)
