"""nerfstudio's own smoke procedure for methods, run on every method we register.

nerfstudio tests each of its methods by reducing the preset (CPU, 2 iterations, 4 rays, one
image to sample from, the torch implementation, a one-view Blender scene) and running its
``train_loop``. A plugin method should pass the same procedure at its *preset* settings: this
is what caught presets whose SP schedule ended at an absolute step after such a short run.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from sp_plugins.nerfstudio.runs import method_config, our_methods

METHODS = sorted(our_methods())


@pytest.fixture(scope="module")
def one_view_scene(tmp_path_factory) -> Path:
    from sp_plugins.data import make_tiny_scene

    scene = make_tiny_scene(tmp_path_factory.mktemp("one-view") / "sphere", mesh="sphere", n_train=1, n_val=1, n_test=1)
    return scene.root / "blender"


def reduced_config(name: str, data: Path, out: Path):
    """nerfstudio's ``set_reduced_config`` (tests/test_train.py), on our preset."""
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig

    config = method_config(name)
    config.machine.num_devices = 1
    config.machine.device_type = "cpu"
    config.max_num_iterations = 2
    config.pipeline.datamanager.dataparser = BlenderDataParserConfig(data=data)
    config.pipeline.datamanager.train_num_images_to_sample_from = 1
    config.pipeline.datamanager.train_num_rays_per_batch = 4
    config.vis = "tensorboard"
    config.output_dir = out
    config.logging.relative_log_dir = Path("logs")
    model = config.pipeline.model
    if hasattr(model, "implementation"):
        model.implementation = "torch"
    if hasattr(model, "num_coarse_samples"):
        model.num_coarse_samples = 4
    if hasattr(model, "num_importance_samples"):
        model.num_importance_samples = 4
    config.viewer.quit_on_train_completion = True
    return config


def test_every_registered_method_is_covered():
    assert len(METHODS) == 12 and {"sp-neus-hashgrid", "sp-mipnerf", "sp-relu-field", "sp-nerfacto"} <= set(METHODS)


@pytest.mark.parametrize("name", METHODS)
def test_nerfstudio_reduced_config_trains(name, one_view_scene, tmp_path):
    from nerfstudio.scripts.train import train_loop

    config = reduced_config(name, one_view_scene, tmp_path)
    train_loop(local_rank=0, world_size=1, config=config)
    checkpoints = sorted(config.get_checkpoint_dir().glob("step-*.ckpt"))
    assert checkpoints, f"{name}: the 2-iteration run wrote no checkpoint"
