"""relu-field: a dense ReLU field trained coarse-to-fine (4 stages, grid upsampled and optimizer reset per stage)."""

from sp_plugins.nerfstudio.radiance_configs import relu_field_method

relu_field = relu_field_method(
    "relu-field",
    stages=4,
    sp=False,
    description="ReLU field (dense grid, ReLU after trilinear interpolation), original 4-stage coarse-to-fine.",
)
