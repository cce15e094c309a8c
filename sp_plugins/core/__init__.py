"""Stochastic preconditioning core: torch only, no host imports."""

from sp_plugins.core.alpha_grid import AlphaGrid
from sp_plugins.core.boundary import BOUNDARY_KINDS, apply_boundary, reflect
from sp_plugins.core.config import SPConfig
from sp_plugins.core.noise import NOISE_KINDS, sample_noise
from sp_plugins.core.perturb import perturb, perturbed_mean
from sp_plugins.core.preconditioner import StochasticPreconditioner
from sp_plugins.core.run import SPNotReached, SPRun
from sp_plugins.core.schedule import SCHEDULE_KINDS, AlphaSchedule
from sp_plugins.core.stencil import (
    STENCIL_KINDS,
    finite_differences,
    stencil_gradient,
    stencil_laplacian,
    stencil_offsets,
    stencil_points,
)

__all__ = [
    "SPNotReached",
    "SPRun",
    "AlphaGrid",
    "AlphaSchedule",
    "BOUNDARY_KINDS",
    "NOISE_KINDS",
    "SCHEDULE_KINDS",
    "STENCIL_KINDS",
    "SPConfig",
    "StochasticPreconditioner",
    "apply_boundary",
    "finite_differences",
    "perturb",
    "perturbed_mean",
    "reflect",
    "sample_noise",
    "stencil_gradient",
    "stencil_laplacian",
    "stencil_offsets",
    "stencil_points",
]
