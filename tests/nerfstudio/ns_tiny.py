"""CPU-sized versions of our SDF method configs, shared by the nerfstudio tests.

A plain module (not conftest) so tests can import it by a name no other test folder uses.
"""

from __future__ import annotations

from pathlib import Path

from sp_plugins.nerfstudio.runs import configure_run, method_config

SDF_METHODS = ("sp-neus", "neus-hashgrid", "sp-neus-hashgrid", "neuralangelo-lite", "sp-neuralangelo-lite")


def shrink_sdf_model(config) -> None:
    """Small MLPs, a small grid and few samples: seconds per run on one CPU thread."""
    model = config.pipeline.model
    field = model.sdf_field
    field.hidden_dim = 32 if field.use_grid_feature else 48
    field.num_layers = 2
    field.hidden_dim_color = 32
    field.geo_feat_dim = 15
    field.num_levels = 8
    field.max_res = 64
    field.log2_hashmap_size = 12
    model.num_samples = 16
    model.num_samples_importance = 8
    model.num_up_sample_steps = 1
    model.background_model = "none"
    model.background_color = "white"
    model.eval_num_rays_per_chunk = 256
    if hasattr(model, "c2f_init_levels"):
        model.c2f_init_levels = 2


def _tiny_config(name: str, scene: Path, out: Path, *, layout: str = "blender", steps: int = 3, **sp):
    config = method_config(name)
    shrink_sdf_model(config)
    for key, value in sp.items():
        setattr(config.pipeline.model.sp, key, value)
    configure_run(config, scene / layout, steps=steps, output_dir=out, layout=layout, rays_per_batch=32)
    return config


def run_recording(config, stop_after=None):
    """Train with the real trainer, recording each iteration's loss and metrics."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

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

        def stop(step):
            trainer.stop_training = True

        trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], stop, iters=(stop_after,)))
    trainer.train()
    return trainer, record
