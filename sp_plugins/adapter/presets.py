"""The paper's SP settings per method family (Ling et al. 2025), shared by both hosts.

Schedule ends are fractions of training, so a shortened run keeps its shape; pass
``--pipeline.model.sp.end STEP`` (> 1) for an absolute step. Alphas are in scene units.
"""

from __future__ import annotations

from sp_plugins.core import SPConfig

NEUS = SPConfig(alpha0=0.013, end=0.2, schedule="exponential")
"""NeuS, NeuS-hashgrid, neus-facto: alpha0 0.013, exponential to 0 over the first 20k of 100k steps."""

NEURALANGELO = SPConfig(alpha0=0.03, end=0.3, schedule="exponential", alpha_grid_init=0.03, alpha_grid_lr=1e-3,
                        alpha_grid_mode="replace", alpha_grid_parameterization="log")
"""Neuralangelo, bakedangelo: alpha0 0.03, exponential to 0 over the first 150k of 500k steps; or
(``--pipeline.model.sp.alpha-grid True``) the paper's spatially adaptive variant: a learnable alpha
grid initialised to 0.03, Adam lr 1e-3, *in place of* the annealed scalar for the same first 30%
(the grid alone, not times the schedule), then SP off. The grid stores log-alpha, so lr 1e-3 is a
0.1% relative step (the paper's alpha-stored grid moves 0.001 in scene units per step): see
``AlphaGrid`` and docs/results/alpha-grid.md."""

MIPNERF = SPConfig(alpha0=0.04, end=1 / 3, schedule="exponential", boundary="none")
"""Sparse-view MipNeRF: alpha0 0.04, exponential to 0 by step 2500, a third of the sp-mipnerf preset's
7500 steps. NeRF MLPs are defined everywhere, so there is no box to reflect into."""

RELU_FIELD_STEPS = 28_000
RELU_FIELD = SPConfig(alpha0=0.003, end=8000 / RELU_FIELD_STEPS, schedule="exponential", boundary="reflect")
"""ReLU fields: alpha0 0.003 over the first 8000 of 28000 steps."""

POSITION_FIELD = SPConfig(alpha0=0.02, end=0.2, schedule="exponential", boundary="none")
"""Any field that reads sample positions (nerfacto, vanilla NeRF, TensoRF, a plugin's field): not
from the paper, which does not run these hosts. About 0.5-1% of a Blender or nerfstudio scene's box
diagonal, exponential to 0 over the first 20% of training; no reflection, so it is safe in
contracted (unbounded) scenes. Bounded fields do better with ``--pipeline.model.sp.boundary reflect``."""

BOX_FIELD = SPConfig(alpha0=0.02, end=0.2, schedule="exponential", boundary="reflect")
"""A field that lives in the scene box (TensoRF's grid): :data:`POSITION_FIELD`, reflected into the box."""
DEFAULT = POSITION_FIELD
"""What ``with_sp`` / ``sp-train`` use for a method we have no preset for."""
