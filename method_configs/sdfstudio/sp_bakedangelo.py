"""sp-bakedangelo: sdfstudio's bakedangelo with stochastic preconditioning instead of coarse-to-fine."""

from sp_plugins.sdfstudio.neus import SPBakedAngeloModelConfig
from sp_plugins.sdfstudio.sdf_methods import NEURALANGELO_SP, sp_method

sp_bakedangelo = sp_method(
    "bakedangelo", SPBakedAngeloModelConfig, NEURALANGELO_SP,
    "sdfstudio bakedangelo, coarse-to-fine replaced by stochastic preconditioning (alpha0 0.03, first 30%).",
    replace_coarse_to_fine=True,
)
