"""sp-neus: NeuS (frequency encoding) with stochastic preconditioning."""

from sp_plugins.nerfstudio.sdf_configs import neus_method

sp_neus = neus_method(
    "sp-neus",
    hash_grid=False,
    sp=True,
    description="NeuS (frequency encoding) + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
