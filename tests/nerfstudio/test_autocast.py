"""The mixed-precision path: one training step of sp-nerfacto and ``sp-train nerfacto``
under autocast, our hash grid and the seam inside it.

nerfstudio's trainer turns ``--mixed-precision`` off on a CPU; the test switches it back on after
set-up, so ``train_iteration`` runs under ``torch.autocast("cpu")`` (bfloat16), the CPU's form of the
fp16 autocast a GPU run uses (``sp-gpu-check`` runs that one). The loss must be finite, the field
must be handed samples that moved, and the moved positions must stay float32 (a half-precision
position would round a small offset away).
"""

from __future__ import annotations

import math

import pytest
import torch
from tests.helpers.ns_configs import in_process_data, shrink_model, sp_train_config
from tests.helpers.ns_configs import tiny_radiance_config

from sp_plugins.nerfstudio.runs import configure_run


def config_for(name, scene, out):
    if name == "sp-train:nerfacto":
        config = sp_train_config("nerfacto")
        shrink_model(config.pipeline.model)
        in_process_data(config)
        config.pipeline.model.sp.alpha0 = 0.05
        return configure_run(config, scene / "blender", steps=4, output_dir=out, rays_per_batch=64)
    return tiny_radiance_config(name, scene, out, steps=4)


@pytest.mark.parametrize("name", ["sp-nerfacto", "sp-train:nerfacto"])
def test_a_mixed_precision_step_is_finite_and_perturbed_in_float32(name, tiny_scene, tmp_path, monkeypatch):
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    from sp_plugins.nerfstudio import seam

    handed = []
    plain = seam.perturbed_samples

    def recording(samples, sp, *read):
        moved = plain(samples, sp, *read)
        handed.append((torch.is_autocast_cpu_enabled(), moved.frustums.get_positions().dtype,
                       float((moved.frustums.get_positions() - samples.frustums.get_positions()).abs().max())))
        return moved

    monkeypatch.setattr(seam, "perturbed_samples", recording)
    config = config_for(name, tiny_scene, tmp_path)
    config.mixed_precision = True
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.mixed_precision = True  # the trainer switched it off for the CPU; autocast("cpu") is bfloat16
    for callback in trainer.callbacks:
        callback.run_callback_at_location(0, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    trainer.pipeline.train()
    loss, loss_dict, _ = trainer.train_iteration(0)
    assert math.isfinite(float(loss)) and all(math.isfinite(float(v)) for v in loss_dict.values())
    assert handed, "no field was handed moved samples"
    assert all(autocast for autocast, _, _ in handed), "the step did not run under autocast"
    assert all(dtype == torch.float32 and move > 0 for _, dtype, move in handed), handed
