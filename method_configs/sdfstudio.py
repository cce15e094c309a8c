"""Our sdfstudio (commit 370902a) methods, one attribute each (entry points of our group
``sp_plugins.sdfstudio_methods`` in pyproject.toml, read by :mod:`sp_plugins.sdfstudio.registration`):
sdfstudio's own configs through the generic conversion, with fixed names and descriptions. Their SP
settings are the table's (:func:`sp_plugins.sdfstudio.table.preset_for`: Neuralangelo's where the
host enables coarse-to-fine, which SP then replaces; NeuS's otherwise)."""

from sp_plugins.sdfstudio.registration import sp_method

sp_neus = sp_method(
    "neus", None,
    "sdfstudio NeuS + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
"""sp-neus: sdfstudio's NeuS with stochastic preconditioning (the generic conversion, NeuS preset)."""

sp_neus_facto = sp_method(
    "neus-facto", None,
    "sdfstudio neus-facto + stochastic preconditioning (alpha0 0.013, to 0 over the first 20%).",
)
"""sp-neus-facto: sdfstudio's neus-facto with stochastic preconditioning (the generic conversion, NeuS preset)."""

sp_neuralangelo = sp_method(
    "neuralangelo", None,
    "sdfstudio Neuralangelo, coarse-to-fine replaced by stochastic preconditioning (alpha0 0.03, first 30%).",
)
"""sp-neuralangelo: sdfstudio's Neuralangelo with stochastic preconditioning instead of coarse-to-fine
(the generic conversion, Neuralangelo preset; coarse-to-fine is replaced because the host enables it)."""

sp_bakedangelo = sp_method(
    "bakedangelo", None,
    "sdfstudio bakedangelo, coarse-to-fine replaced by stochastic preconditioning (alpha0 0.03, first 30%).",
)
"""sp-bakedangelo: sdfstudio's bakedangelo with stochastic preconditioning instead of coarse-to-fine
(the generic conversion, Neuralangelo preset; coarse-to-fine is replaced because the host enables it)."""
