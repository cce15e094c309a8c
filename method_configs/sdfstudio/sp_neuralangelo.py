"""sp-neuralangelo: sdfstudio's Neuralangelo with stochastic preconditioning instead of coarse-to-fine."""

from sp_plugins.sdfstudio.neus import SPNeuralangeloModelConfig
from sp_plugins.sdfstudio.sdf_methods import NEURALANGELO_SP, sp_method

sp_neuralangelo = sp_method(
    "neuralangelo", SPNeuralangeloModelConfig, NEURALANGELO_SP,
    "sdfstudio Neuralangelo, coarse-to-fine replaced by stochastic preconditioning (alpha0 0.03, first 30%).",
    replace_coarse_to_fine=True,
)
