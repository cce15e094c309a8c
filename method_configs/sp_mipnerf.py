"""sp-mipnerf: MipNeRF with the SP offset on each conical frustum's Gaussian mean."""

from sp_plugins.nerfstudio.radiance_configs import mipnerf_method

sp_mipnerf = mipnerf_method(
    "sp-mipnerf",
    sp=True,
    description="MipNeRF + stochastic preconditioning on the Gaussian means (alpha0 0.04, to 0 by step 2500); "
    "sparse views with --pipeline.datamanager.train-views N.",
)
