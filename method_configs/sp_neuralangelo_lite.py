"""sp-neuralangelo-lite: neuralangelo-lite without coarse-to-fine, stochastic preconditioning instead."""

from sp_plugins.nerfstudio.sdf_configs import neuralangelo_method

sp_neuralangelo_lite = neuralangelo_method(
    "sp-neuralangelo-lite",
    sp=True,
    description="Neuralangelo-lite, all levels from step 0 + SP (alpha0 0.03 over 30%; --pipeline.model.sp.alpha-grid True for a learnable alpha grid).",
)
