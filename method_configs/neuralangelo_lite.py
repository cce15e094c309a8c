"""neuralangelo-lite: hash grid, numerical gradients, curvature + eikonal losses, coarse-to-fine."""

from sp_plugins.nerfstudio.sdf_configs import neuralangelo_method

neuralangelo_lite = neuralangelo_method(
    "neuralangelo-lite",
    sp=False,
    description="Neuralangelo on NeuS's renderer: numerical gradients, curvature loss, progressive levels and step.",
)
