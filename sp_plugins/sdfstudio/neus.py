"""The SP classes of sdfstudio's NeuS family under their old names (aliases).

sp-neus, sp-neus-facto, sp-neuralangelo and sp-bakedangelo are now made by the generic
conversion (:func:`sp_plugins.sdfstudio.registration.with_sp`), whose model and model config classes are
the variants of :mod:`sp_plugins.sdfstudio.variants` (``SPModelConfig__nerfstudio_dmodels_...``).
A ``config.yml`` written before names these classes by their old paths
(``sp_plugins.sdfstudio.neus.SPNeuSModelConfig``...), so the names stay importable here and are
the same classes: such a run loads in ``ns-eval`` / ``ns-extract-mesh`` as before.

One difference: the class *defaults* of the Neuralangelo pair's configs are now the host's
(``enable_progressive_hash_encoding=True``...); the method configs set SP's values, and a saved
``config.yml`` holds every field, so neither training nor loading changes.
"""

from __future__ import annotations

from nerfstudio.models.bakedangelo import BakedAngeloModel, BakedAngeloModelConfig
from nerfstudio.models.neuralangelo import NeuralangeloModel, NeuralangeloModelConfig
from nerfstudio.models.neus import NeuSModel, NeuSModelConfig
from nerfstudio.models.neus_facto import NeuSFactoModel, NeuSFactoModelConfig

from sp_plugins.sdfstudio.variants import variant

SPNeuSModelConfig = variant("ModelConfig", NeuSModelConfig)
SPNeuSModel = variant("Model", NeuSModel)
SPNeuSFactoModelConfig = variant("ModelConfig", NeuSFactoModelConfig)
SPNeuSFactoModel = variant("Model", NeuSFactoModel)
SPNeuralangeloModelConfig = variant("ModelConfig", NeuralangeloModelConfig)
SPNeuralangeloModel = variant("Model", NeuralangeloModel)
SPBakedAngeloModelConfig = variant("ModelConfig", BakedAngeloModelConfig)
SPBakedAngeloModel = variant("Model", BakedAngeloModel)

__all__ = [
    "SPBakedAngeloModel",
    "SPBakedAngeloModelConfig",
    "SPNeuSFactoModel",
    "SPNeuSFactoModelConfig",
    "SPNeuSModel",
    "SPNeuSModelConfig",
    "SPNeuralangeloModel",
    "SPNeuralangeloModelConfig",
]
