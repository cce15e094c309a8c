"""No host-device sync of ours inside a training step of any nerfstudio method.

Each method trains with nerfstudio's trainer; the body of the training loop (the callbacks before,
``train_iteration``, the callbacks after) runs under :class:`sp_plugins.sync_count.SyncCounter` for
two steady-state steps (not the first, which checks that SP reached a field once, and not a
logging, checkpoint or last step, where the non-finite check reads its device flag). Any operator
that would stall a CUDA stream at a site inside sp_plugins fails the test; the host's own sites
(nerfstudio's pixel sampler, cameras, NeuS sampler) are printed, not judged.
"""

from __future__ import annotations

import pytest
from tests.helpers.ns_configs import in_process_data, shrink_model, sp_train_config
from tests.helpers.ns_configs import tiny_sdf_config
from tests.helpers.ns_configs import tiny_radiance_config

from sp_plugins.nerfstudio.runs import configure_run
from sp_plugins.sync_count import SyncCounter

STEPS = 5
COUNTED = (1, 2)

OURS = ("sp-neus-hashgrid", "sp-neuralangelo-lite", "sp-mipnerf", "sp-relu-field", "sp-nerfacto", "sp-train:nerfacto")


def config_for(name, scene, out):
    sp = dict(alpha0=0.05, end=1.0, seed=0)
    if name.startswith("sp-train:"):
        config = sp_train_config(name.split(":", 1)[1])
        shrink_model(config.pipeline.model)
        in_process_data(config)
        for key, value in sp.items():
            setattr(config.pipeline.model.sp, key, value)
        return configure_run(config, scene / "blender", steps=STEPS, output_dir=out, rays_per_batch=64)
    if name in ("sp-neus-hashgrid", "sp-neuralangelo-lite"):
        return tiny_sdf_config(name, scene, out, steps=STEPS, **sp)
    return tiny_radiance_config(name, scene, out, steps=STEPS, **sp)


def steady_state_syncs(config) -> SyncCounter:
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    config.mixed_precision = False
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    counter = SyncCounter()
    for step in range(3):
        trainer.pipeline.train()
        with counter if step in COUNTED else _nothing():
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            trainer.train_iteration(step)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    assert trainer.pipeline.model.sp.alpha > 0  # SP was on in the counted steps
    return counter


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.mark.parametrize("name", OURS)
def test_a_training_step_has_no_sync_of_ours(name, tiny_scene, tmp_path):
    from sp_plugins.core.boundary import dense_fold

    with dense_fold():  # the fold a GPU run takes (the CPU's sparse fold syncs on purpose)
        counter = steady_state_syncs(config_for(name, tiny_scene, tmp_path))
    print(f"{name}: per {len(COUNTED)} steps\n{counter.report()}")
    assert not counter.ours(), f"{name}: host-device syncs inside sp_plugins per step: {counter.ours()}"
