"""sp-neus: sdfstudio's NeuS with stochastic preconditioning (the generic conversion, NeuS preset)."""

from sp_plugins.sdfstudio.conversion import NEUS_SP, sp_method

sp_neus = sp_method(
    "neus", NEUS_SP,
    "sdfstudio NeuS + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
