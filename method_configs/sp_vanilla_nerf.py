"""sp-vanilla-nerf: NeRF (coarse + fine MLPs) with SP through frustum offsets."""

from sp_plugins.nerfstudio.radiance_configs import vanilla_nerf_method

sp_vanilla_nerf = vanilla_nerf_method(
    "sp-vanilla-nerf", description="Vanilla NeRF + stochastic preconditioning of the sample positions (frustum offsets)."
)
