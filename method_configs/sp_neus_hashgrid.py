"""sp-neus-hashgrid: NeuS on the paper's hash grid with stochastic preconditioning."""

from sp_plugins.nerfstudio.sdf_configs import neus_method

sp_neus_hashgrid = neus_method(
    "sp-neus-hashgrid",
    hash_grid=True,
    sp=True,
    description="NeuS-hashgrid + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
