"""CPU-sized nerfstudio trainer configs for the tests: our SDF methods (:func:`tiny_sdf_config`), our
radiance methods (:func:`tiny_radiance_config`), nerfstudio's built-in methods under ``sp-train``
(:func:`sp_train_config`, :func:`shrink_model`), and :func:`run_recording`, which trains one with the
real trainer recording each step."""

from __future__ import annotations

from pathlib import Path

from sp_plugins.adapter.shrink import shrink
from sp_plugins.nerfstudio.runs import configure_run, method_config

SDF_METHODS = ("sp-neus", "neus-hashgrid", "sp-neus-hashgrid", "neuralangelo-lite", "sp-neuralangelo-lite")


def shrink_sdf_model(config) -> None:
    """Small MLPs, a small grid and few samples: seconds per run on one CPU thread."""
    grid = config.pipeline.model.sdf_field.use_grid_feature
    extra = {"c2f_init_levels": 2} if hasattr(config.pipeline.model, "c2f_init_levels") else {}
    shrink(config, num_samples=16, num_samples_importance=8, num_up_sample_steps=1, background_model="none",
           background_color="white", eval_num_rays_per_chunk=256, **extra,
           field=dict(hidden_dim=32 if grid else 48, num_layers=2, hidden_dim_color=32, geo_feat_dim=15, num_levels=8,
                      max_res=64, log2_hashmap_size=12))


def tiny_sdf_config(name: str, scene: Path, out: Path, *, layout: str = "blender", steps: int = 3, **sp):
    """``name`` (one of :data:`SDF_METHODS`) shrunk to a few CPU seconds, ``steps`` steps on ``scene / layout``,
    written under ``out``; ``sp`` sets fields of the SP config."""
    config = method_config(name)
    shrink_sdf_model(config)
    for key, value in sp.items():
        setattr(config.pipeline.model.sp, key, value)
    configure_run(config, scene / layout, steps=steps, output_dir=out, layout=layout, rays_per_batch=32)
    return config


def stop_after_step(trainer, step: int) -> None:
    """``trainer`` stops after iteration ``step`` (a training callback)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    def stop(step):  # (nerfstudio requires the argument's name)
        trainer.stop_training = True

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], stop, iters=(step,)))


def run_recording(config, stop_after=None):
    """Train with the real trainer, recording each iteration's loss and metrics."""
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    record = []
    original = trainer.train_iteration

    def recording(step):
        loss, loss_dict, metrics = original(step)
        record.append((float(loss), {k: float(v) for k, v in loss_dict.items()}, metrics))
        return loss, loss_dict, metrics

    trainer.train_iteration = recording
    if stop_after is not None:
        stop_after_step(trainer, stop_after)
    trainer.train()
    return trainer, record


# -- our radiance methods ---------------------------------------------------------------------------
def shrink_radiance_model(name: str, config) -> None:
    """Few samples, tiny grids and tables: a fraction of a second per iteration on one thread."""
    if "relu-field" in name:
        shrink(config, resolution=17, num_samples=16)
    elif name in ("sp-mipnerf", "sp-vanilla-nerf", "freenerf-lite"):
        shrink(config, num_coarse_samples=8, num_importance_samples=8)
    elif name == "sp-nerfacto":
        proposal = {"hidden_dim": 8, "log2_hashmap_size": 10, "num_levels": 3, "max_res": 32, "use_linear": False}
        shrink(config, num_nerf_samples_per_ray=8, num_proposal_samples_per_ray=(8, 8), log2_hashmap_size=12, max_res=64,
               hidden_dim=16, proposal_net_args_list=[dict(proposal), dict(proposal)])
        config.pipeline.model.camera_optimizer.mode = "off"
    elif name == "sp-tensorf":
        shrink(config, init_resolution=16, final_resolution=24, upsampling_iters=(2,), num_samples=8, num_uniform_samples=16,
               num_den_components=4, num_color_components=8)
    shrink(config, eval_num_rays_per_chunk=512)


def tiny_radiance_config(name, scene, out, *, steps=3, rays=64, layout="blender", **sp):
    config = method_config(name)
    shrink_radiance_model(name, config)
    for key, value in {"alpha0": 0.05, "end": 1.0, **sp}.items():
        setattr(config.pipeline.model.sp, key, value)
    configure_run(config, scene / layout, steps=steps, output_dir=out, layout=layout, rays_per_batch=rays)
    return config


# -- nerfstudio's built-in methods under sp-train (also the README table) ---------------------------
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
