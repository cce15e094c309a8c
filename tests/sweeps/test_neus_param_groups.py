"""NeuS-hashgrid: the hash-grid tables and the MLPs are separate optimizer groups, so their
learning rates can be swept apart; by default both get the same settings."""

from __future__ import annotations

import pytest
import torch

from sp_plugins.nerfstudio.neus import GRID_GROUP

TINY = ["--machine.device-type", "cpu", "--max-num-iterations", "2", "--vis", "tensorboard",
        "--pipeline.datamanager.train-num-rays-per-batch", "32", "--pipeline.model.num-samples", "8",
        "--pipeline.model.num-samples-importance", "8", "--pipeline.model.num-up-sample-steps", "1",
        "--pipeline.model.background-model", "none", "--pipeline.model.sdf-field.hidden-dim", "16",
        "--pipeline.model.sdf-field.hidden-dim-color", "16", "--pipeline.model.sdf-field.geo-feat-dim", "7",
        "--pipeline.model.sdf-field.num-levels", "4", "--pipeline.model.sdf-field.log2-hashmap-size", "10",
        "--pipeline.model.sdf-field.max-res", "32"]


def _trainer(args, tmp_path):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    config = tyro.cli(AnnotatedBaseConfigUnion, args=[args[0], "--output-dir", str(tmp_path), *args[1:]])
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return config, trainer


def _initial_lr(trainer, group: str) -> float:
    return trainer.optimizers.optimizers[group].param_groups[0]["initial_lr"]


@pytest.mark.parametrize("method", ["neus-hashgrid", "sp-neus-hashgrid"])
def test_grid_tables_have_their_own_group_with_the_same_default_lr(method, sweep_scene, tmp_path):
    config, trainer = _trainer([method, *TINY, "blender-data", "--data", str(sweep_scene / "blender")], tmp_path)
    assert config.optimizers[GRID_GROUP]["optimizer"].lr == config.optimizers["fields"]["optimizer"].lr
    assert _initial_lr(trainer, GRID_GROUP) == _initial_lr(trainer, "fields")
    model = trainer.pipeline.model
    groups = model.get_param_groups()
    grid_ids = {id(p) for p in model.field.encoding.parameters()}
    assert grid_ids and {id(p) for p in groups[GRID_GROUP]} == grid_ids
    assert not grid_ids & {id(p) for p in groups["fields"]}, "a grid table is also in the MLP group"
    every = {id(p) for p in model.field.parameters()}
    assert {id(p) for p in groups["fields"]} | grid_ids == every, "a field parameter is in no group"


def test_grid_lr_flag_reaches_the_grid_optimizer_only(sweep_scene, tmp_path):
    args = ["neus-hashgrid", *TINY, "--optimizers.field-grid.optimizer.lr", "0.02",
            "--optimizers.fields.optimizer.lr", "0.001", "--optimizers.field-grid.scheduler.warm-up-end", "1",
            "blender-data", "--data", str(sweep_scene / "blender")]
    _, trainer = _trainer(args, tmp_path)
    assert _initial_lr(trainer, GRID_GROUP) == pytest.approx(0.02)
    assert _initial_lr(trainer, "fields") == pytest.approx(0.001)
    tables = trainer.optimizers.optimizers[GRID_GROUP].param_groups[0]["params"]
    before = [t.detach().clone() for t in tables]
    for step in range(3):  # past the first step's zero warm-up factor
        trainer.train_iteration(step)
    assert any(not torch.equal(b, t.detach()) for b, t in zip(before, tables)), "the grid optimizer did not update the tables"


def test_frequency_neus_has_no_grid_group(sweep_scene, tmp_path):
    i = TINY.index("--pipeline.model.sdf-field.num-levels")
    args = ["sp-neus", *TINY[:i], *TINY[i + 2:], "--pipeline.model.sdf-field.num-layers", "2",  # 8 layers need width > 39
            "blender-data", "--data", str(sweep_scene / "blender")]
    _, trainer = _trainer(args, tmp_path)
    assert GRID_GROUP not in trainer.optimizers.optimizers
