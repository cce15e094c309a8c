"""The ReLU field (Karnewar et al. 2022) as a nerfstudio method of ours, not a host's.

A dense grid, trilinear interpolation, ReLU after interpolation (:mod:`.field`); the model with its
coarse-to-fine hierarchy or SP from step 0 (:mod:`.model`); thr3ed_atom's per-stage learning-rate
schedule (:mod:`.lr`). The methods ``relu-field``, ``relu-field-flat`` and ``sp-relu-field`` are
built in :mod:`sp_plugins.nerfstudio.radiance_configs`.
"""
