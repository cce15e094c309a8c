"""sp-tensorf: TensoRF with SP on the sample positions, reflected inside the scene box."""

from sp_plugins.nerfstudio.radiance_configs import tensorf_method

sp_tensorf = tensorf_method(
    "sp-tensorf", description="TensoRF + stochastic preconditioning of the sample positions, reflected in the scene box."
)
