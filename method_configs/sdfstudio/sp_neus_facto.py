"""sp-neus-facto: sdfstudio's neus-facto with stochastic preconditioning (the generic conversion, NeuS preset)."""

from sp_plugins.adapter import presets
from sp_plugins.sdfstudio.registration import sp_method

sp_neus_facto = sp_method(
    "neus-facto", presets.NEUS,
    "sdfstudio neus-facto + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
