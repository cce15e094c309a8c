"""freenerf-lite: MipNeRF + FreeNeRF's frequency and occlusion regularisation (SP off; sp-train adds it)."""

from sp_plugins.nerfstudio.freenerf import freenerf_method

freenerf_lite = freenerf_method(
    "freenerf-lite",
    description="FreeNeRF on nerfstudio's MipNeRF: position-encoding bands opened linearly over the first 70% of "
    "training, density near the cameras penalised; sparse views with --pipeline.datamanager.train-views N. "
    "sp-train freenerf-lite adds stochastic preconditioning.",
)
