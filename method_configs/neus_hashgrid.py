"""neus-hashgrid: NeuS on the paper's hash grid, no SP (the baseline of sp-neus-hashgrid)."""

from sp_plugins.nerfstudio.sdf_configs import neus_method

neus_hashgrid = neus_method(
    "neus-hashgrid",
    hash_grid=True,
    sp=False,
    description="NeuS with a hash grid (16 levels, 16-2048, 2^19, 2 features); runs without tiny-cuda-nn.",
)
