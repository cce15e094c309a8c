"""CPU-sized versions of nerfstudio's own methods under ``sp-train`` (shared by tests and the README table)."""

from __future__ import annotations

SMALL = dict(
    num_nerf_samples_per_ray=8, num_proposal_samples_per_ray=(8, 8), log2_hashmap_size=12, max_res=64, hidden_dim=16,
    hidden_dim_color=16, hidden_dim_transient=16, num_coarse_samples=8, num_importance_samples=8, eval_num_rays_per_chunk=256,
    init_resolution=16, final_resolution=32, num_samples=8, num_uniform_samples=16, num_den_components=4,
    num_color_components=4, appearance_dim=8,
)
"""Model settings that make one step a fraction of a second (set only where the model has them)."""


def shrink_model(model) -> None:
    for key, value in SMALL.items():
        if hasattr(model, key):
            setattr(model, key, value)
    if hasattr(model, "camera_optimizer") and model.camera_optimizer is not None:
        model.camera_optimizer.mode = "off"
    if hasattr(model, "proposal_net_args_list"):
        for args in model.proposal_net_args_list:
            args.update(log2_hashmap_size=10, max_res=32, hidden_dim=8)
    if hasattr(model, "upsampling_iters"):
        model.upsampling_iters = ()
