"""Our nerfstudio methods, one attribute each (entry points of ``nerfstudio.method_configs`` in
pyproject.toml name ``sp_plugins.method_configs.nerfstudio:<attribute>``).

nerfstudio imports this module in every ``ns-*`` command, also when the user trains a method that is
not ours, so importing it only builds the method configs: no exception hook, no warning filters, no
patched host module. What our methods need is installed when one of them is built or by our own
commands (``sp-train`` installs the start-up patch of :mod:`sp_plugins.patches.nerfstudio_external_methods`).
The configs themselves are built in :mod:`~sp_plugins.nerfstudio.sdf_configs`,
:mod:`~sp_plugins.nerfstudio.radiance_configs` and :mod:`~sp_plugins.nerfstudio.freenerf`; their SP
settings come from :mod:`~sp_plugins.nerfstudio.table`.
"""

from sp_plugins.nerfstudio.freenerf import freenerf_method
from sp_plugins.nerfstudio.radiance_configs import (
    mipnerf_method,
    nerfacto_method,
    relu_field_method,
    tensorf_method,
    vanilla_nerf_method,
)
from sp_plugins.nerfstudio.sdf_configs import neuralangelo_method, neus_method

sp_neus = neus_method(
    "sp-neus",
    hash_grid=False,
    sp=True,
    description="NeuS (frequency encoding) + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
"""sp-neus: NeuS (frequency encoding) with stochastic preconditioning."""

neus_hashgrid = neus_method(
    "neus-hashgrid",
    hash_grid=True,
    sp=False,
    description="NeuS with a hash grid (16 levels, 16-2048, 2^19, 2 features); runs without tiny-cuda-nn.",
)
"""neus-hashgrid: NeuS on the paper's hash grid, no SP (the baseline of sp-neus-hashgrid)."""

sp_neus_hashgrid = neus_method(
    "sp-neus-hashgrid",
    hash_grid=True,
    sp=True,
    description="NeuS-hashgrid + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
"""sp-neus-hashgrid: NeuS on the paper's hash grid with stochastic preconditioning."""

neuralangelo_lite = neuralangelo_method(
    "neuralangelo-lite",
    sp=False,
    description="Neuralangelo on NeuS's renderer: numerical gradients, curvature loss, progressive levels and step.",
)
"""neuralangelo-lite: hash grid, numerical gradients, curvature + eikonal losses, coarse-to-fine."""

sp_neuralangelo_lite = neuralangelo_method(
    "sp-neuralangelo-lite",
    sp=True,
    description="Neuralangelo-lite, all levels from step 0 + SP (alpha0 0.03 over 30%; --pipeline.model.sp.alpha-grid True for a learnable alpha grid).",
)
"""sp-neuralangelo-lite: neuralangelo-lite without coarse-to-fine, stochastic preconditioning instead."""

relu_field = relu_field_method(
    "relu-field",
    stages=4,
    sp=False,
    description="ReLU field (dense grid, ReLU after trilinear interpolation), original 4-stage coarse-to-fine.",
)
"""relu-field: a dense ReLU field trained coarse-to-fine (4 stages, grid upsampled and optimizer reset per stage)."""

relu_field_flat = relu_field_method(
    "relu-field-flat",
    stages=1,
    sp=False,
    description="ReLU field at full resolution from step 0 (no coarse-to-fine): the baseline that collapses into floaters.",
)
"""relu-field-flat: the ReLU field at full resolution from step 0, no hierarchy, no SP."""

sp_relu_field = relu_field_method(
    "sp-relu-field",
    stages=1,
    sp=True,
    description="ReLU field at full resolution + stochastic preconditioning instead of coarse-to-fine (alpha0 0.003, first 8000 steps).",
)
"""sp-relu-field: the ReLU field at full resolution from step 0 with stochastic preconditioning."""

sp_mipnerf = mipnerf_method(
    "sp-mipnerf",
    sp=True,
    description="MipNeRF + stochastic preconditioning on the Gaussian means (alpha0 0.04, to 0 by step 2500); "
    "sparse views with --pipeline.datamanager.train-views N.",
)
"""sp-mipnerf: MipNeRF with the SP offset on each conical frustum's Gaussian mean."""

sp_vanilla_nerf = vanilla_nerf_method(
    "sp-vanilla-nerf", description="Vanilla NeRF + stochastic preconditioning of the sample positions (frustum offsets)."
)
"""sp-vanilla-nerf: NeRF (coarse + fine MLPs) with SP through frustum offsets."""

sp_nerfacto = nerfacto_method(
    "sp-nerfacto",
    description="Nerfacto + stochastic preconditioning of the field's sample positions (proposal networks unperturbed).",
)
"""sp-nerfacto: nerfacto with SP on the main field's sample positions."""

sp_tensorf = tensorf_method(
    "sp-tensorf", description="TensoRF + stochastic preconditioning of the sample positions, reflected in the scene box."
)
"""sp-tensorf: TensoRF with SP on the sample positions, reflected inside the scene box."""

freenerf_lite = freenerf_method(
    "freenerf-lite",
    description="FreeNeRF on nerfstudio's MipNeRF: position-encoding bands opened linearly over the first 70% of "
    "training, density near the cameras penalised; sparse views with --pipeline.datamanager.train-views N. "
    "sp-train freenerf-lite adds stochastic preconditioning.",
)
"""freenerf-lite: MipNeRF + FreeNeRF's frequency and occlusion regularisation (SP off; sp-train adds it)."""
