"""sp-bakedangelo: sdfstudio's bakedangelo with stochastic preconditioning instead of coarse-to-fine
(the generic conversion, Neuralangelo preset; coarse-to-fine is replaced because the host enables it)."""

from sp_plugins.adapter import presets
from sp_plugins.sdfstudio.registration import sp_method

sp_bakedangelo = sp_method(
    "bakedangelo", presets.NEURALANGELO,
    "sdfstudio bakedangelo, coarse-to-fine replaced by stochastic preconditioning (alpha0 0.03, first 30%).",
)
