"""CPU-sized configs of the radiance methods for tests (imported by the test_* files here)."""

from __future__ import annotations

from ns_tiny import run_recording  # noqa: F401  (re-exported for the radiance tests)

from sp_plugins.nerfstudio.runs import configure_run, method_config


def shrink_radiance_model(name: str, model) -> None:
    """Few samples, tiny grids and tables: a fraction of a second per iteration on one thread."""
    if "relu-field" in name:
        model.resolution, model.num_samples = 17, 16
    elif name in ("sp-mipnerf", "sp-vanilla-nerf", "freenerf-lite"):
        model.num_coarse_samples, model.num_importance_samples = 8, 8
    elif name == "sp-nerfacto":
        model.num_nerf_samples_per_ray, model.num_proposal_samples_per_ray = 8, (8, 8)
        model.log2_hashmap_size, model.max_res, model.hidden_dim = 12, 64, 16
        model.proposal_net_args_list = [
            {"hidden_dim": 8, "log2_hashmap_size": 10, "num_levels": 3, "max_res": 32, "use_linear": False},
            {"hidden_dim": 8, "log2_hashmap_size": 10, "num_levels": 3, "max_res": 32, "use_linear": False},
        ]
        model.camera_optimizer.mode = "off"
    elif name == "sp-tensorf":
        model.init_resolution, model.final_resolution, model.upsampling_iters = 16, 24, (2,)
        model.num_samples, model.num_uniform_samples = 8, 16
        model.num_den_components, model.num_color_components = 4, 8
    model.eval_num_rays_per_chunk = 512


def tiny_radiance_config(name, scene, out, *, steps=3, rays=64, layout="blender", **sp):
    config = method_config(name)
    shrink_radiance_model(name, config.pipeline.model)
    for key, value in {"alpha0": 0.05, "end": 1.0, **sp}.items():
        setattr(config.pipeline.model.sp, key, value)
    configure_run(config, scene / layout, steps=steps, output_dir=out, layout=layout, rays_per_batch=rays)
    return config
