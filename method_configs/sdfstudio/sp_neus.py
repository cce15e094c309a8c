"""sp-neus: sdfstudio's NeuS with stochastic preconditioning (the generic conversion, NeuS preset)."""

from sp_plugins.adapter import presets
from sp_plugins.sdfstudio.registration import sp_method

sp_neus = sp_method(
    "neus", presets.NEUS,
    "sdfstudio NeuS + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
