"""The settings every ``sp-fit`` task has (its length, seed, learning rate and MLP), and those of the
tasks that end in a mesh (meshing and mesh metrics). Each task's config extends one of them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple


@dataclass
class FitSettings:
    steps: int = 2000
    """Optimisation steps."""
    seed: int = 0
    """Seeds the network initialisation, the batches and (unless sp.seed is set) the SP noise."""
    lr: float = 1e-3
    """Adam learning rate."""
    hidden: Tuple[int, ...] = (64, 64)
    """Widths of the MLP's hidden layers."""


@dataclass
class MeshedFitSettings(FitSettings):
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

    def validate_meshing(self) -> None:
        """Refuse a marching-cubes grid too coarse to mesh, before any training step (not after the last)."""
        if self.mesh_resolution < 8:
            raise ValueError(f"mesh_resolution={self.mesh_resolution}: use at least 8")
