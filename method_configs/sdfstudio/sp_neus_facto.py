"""sp-neus-facto: sdfstudio's neus-facto with stochastic preconditioning (the generic conversion, NeuS preset)."""

from sp_plugins.sdfstudio.conversion import NEUS_SP, sp_method

sp_neus_facto = sp_method(
    "neus-facto", NEUS_SP,
    "sdfstudio neus-facto + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
