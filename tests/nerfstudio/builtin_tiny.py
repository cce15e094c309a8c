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
    field = getattr(model, "sdf_field", None)
    if field is not None:  # the NeuS family: a small SDF MLP and grid, no background model
        for key, value in dict(hidden_dim=32, num_layers=2, hidden_dim_color=32, num_layers_color=2, geo_feat_dim=15,
                               num_levels=8, max_res=64, log2_hashmap_size=12).items():
            setattr(field, key, value)
        for key, value in dict(num_samples=16, num_samples_importance=8, num_up_sample_steps=1, background_model="none").items():
            if hasattr(model, key):
                setattr(model, key, value)
    if hasattr(model, "upsampling_iters"):
        # TensoRF: no upsampling in a short run; not (), which TensoRFModel.update_to_step indexes when a
        # checkpoint loads
        model.upsampling_iters = (10**9,)


def sp_train_config(method: str):
    """A private copy of ``sp-train METHOD``'s trainer config for nerfstudio's built-in ``method``
    (the generic route, :func:`sp_plugins.nerfstudio.registration.sp_methods`)."""
    import copy

    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    from sp_plugins.nerfstudio.registration import sp_methods

    configs, _, refused = sp_methods({method: all_methods[method]}, all_descriptions)
    assert method in configs, f"sp-train refuses {method}: {refused.get(method)}"
    return copy.deepcopy(configs[method])


def in_process_data(config) -> None:
    """Replace a ``ParallelDataManager`` (a spawned worker process: seconds to start on a CPU) by
    nerfstudio's vanilla data manager with the same settings; the model is untouched."""
    import dataclasses

    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
    from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManagerConfig

    dm = config.pipeline.datamanager
    if isinstance(dm, ParallelDataManagerConfig):
        names = [f.name for f in dataclasses.fields(VanillaDataManagerConfig) if f.init and f.name != "_target"]
        kept = {name: getattr(dm, name) for name in names}
        config.pipeline.datamanager = VanillaDataManagerConfig(**kept)
