"""relu-field-flat: the ReLU field at full resolution from step 0, no hierarchy, no SP."""

from sp_plugins.nerfstudio.radiance_configs import relu_field_method

relu_field_flat = relu_field_method(
    "relu-field-flat",
    stages=1,
    sp=False,
    description="ReLU field at full resolution from step 0 (no coarse-to-fine): the baseline that collapses into floaters.",
)
