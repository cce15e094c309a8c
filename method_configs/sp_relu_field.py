"""sp-relu-field: the ReLU field at full resolution from step 0 with stochastic preconditioning."""

from sp_plugins.nerfstudio.radiance_configs import relu_field_method

sp_relu_field = relu_field_method(
    "sp-relu-field",
    stages=1,
    sp=True,
    description="ReLU field at full resolution + stochastic preconditioning instead of coarse-to-fine (alpha0 0.003, first 8000 steps).",
)
