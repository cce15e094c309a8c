"""bench/sdfstudio_failure_regime.py in sdfstudio's environment, at a toy size: the hash tables get an
optimizer group of their own at the setting's grid lr in both runs (sdfstudio keeps them in
``fields``), the SP run takes the setting's alpha0 / end, and the pair trains and reports."""

import dataclasses
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: bench/ is not an installed package
import bench.failure_regime as fr
import bench.sdfstudio_failure_regime as sfr

TOY = fr.Setting(mesh="box", steps=2, views=6, test_views=1, resolution=(24, 18), rays=32, num_samples=8,
                 num_samples_importance=4, hidden_dim=16, num_levels=4, max_res=32, log2_hashmap_size=10,
                 background_mlp=(2, 16), mesh_resolution=16, warm_up_end=1, grid_lr=0.1, sp_alpha0=0.07, sp_end=0.5)


def _ids(optimizer):
    return {id(p) for group in optimizer.param_groups for p in group["params"]}


def test_grid_tables_train_in_their_own_group_at_the_grid_lr(patched, tmp_path):
    import nerfstudio.models.base_surface_model as surface

    from bench.harness.sdfstudio import Run

    original = surface.SurfaceModel.get_param_groups
    scene = sfr.scene_dir(TOY, tmp_path)
    for name in sfr.PAIR:
        with sfr.background_mlp(*TOY.background_mlp), sfr.grid_group():
            run = Run(name, sfr.make_config(name, scene / "sdfstudio", TOY, tmp_path / "runs", "groups"), TOY.seed)
        optimizers = run.trainer.optimizers
        grid = {id(p) for p in run.trainer.pipeline.model.field.encoding.parameters()}
        assert grid and _ids(optimizers.optimizers[sfr.GRID_GROUP]) == grid
        assert grid.isdisjoint(_ids(optimizers.optimizers["fields"])) and _ids(optimizers.optimizers["fields"])
        assert optimizers.config[sfr.GRID_GROUP]["optimizer"].lr == pytest.approx(0.1)
        assert optimizers.config["fields"]["optimizer"].lr == pytest.approx(TOY.lr)
        if name == "sp-neus":
            assert run.trainer.pipeline.model.sp.config.alpha0 == pytest.approx(0.07)
            assert run.trainer.pipeline.model.sp.config.end == pytest.approx(0.5)
    assert surface.SurfaceModel.get_param_groups is original  # the substitution ends with the set-up


def test_pair_trains_and_records_the_grid_lr(patched, tmp_path):
    result = sfr.run_pair(dataclasses.replace(TOY, mesh_resolution=16), tmp_path, "toy")
    assert result["grid_lr_effective"] == pytest.approx(0.1)
    base, sp = (result[name] for name in sfr.PAIR)
    assert len(base["losses"]) == len(sp["losses"]) == TOY.steps
    assert base["losses"][0] != sp["losses"][0]  # the SP run perturbs from the first step
    for metrics in (base, sp):
        assert 0 < metrics["psnr"] < 60 and isinstance(metrics["failed"], bool)


FOX_TOY = dataclasses.replace(TOY, mesh="fox", dtu_like=False)
"""The real fox at the toy model size (its own 45 + 5 views of 135x240)."""


@pytest.fixture(scope="module")
def fox_pair(patched, tmp_path_factory):
    out = tmp_path_factory.mktemp("fox")
    return sfr.run_pair(FOX_TOY, out, "fox-toy"), out


def test_fox_is_converted_by_sdfstudio_and_centred_on_where_its_cameras_look(fox_pair):
    import json

    import numpy as np

    _, out = fox_pair
    root = out / "scenes" / "fox_sdfstudio"
    train, test = (json.loads((root / f / "meta_data.json").read_text()) for f in ("sdfstudio", "sdfstudio_test"))
    assert (len(train["frames"]), len(test["frames"])) == (45, 5)
    names = [f["rgb_path"] for f in test["frames"]]
    assert names == [f"../converted/{i:06d}_rgb.png" for i in (9, 19, 29, 39, 48)]  # nerfstudio's held-out fox views
    c2w = np.array([f["camtoworld"] for f in train["frames"] + test["frames"]])
    assert np.linalg.norm(sfr.focus_point(c2w)) < 0.05
    distance = np.linalg.norm(c2w[:, :3, 3], axis=1)
    assert distance.mean() == pytest.approx(sfr.CAPTURE_CAMERA_DISTANCE, rel=1e-6)
    box = train["scene_box"]
    assert box["near"] < distance.min() - 1 and box["far"] > distance.max() + 1  # the unit sphere inside [near, far]
    assert all((root / "sdfstudio" / f["rgb_path"]).is_file() for f in train["frames"])


def test_fox_pair_trains_and_scores_whole_images_without_a_mesh(fox_pair):
    result, out = fox_pair
    base, sp = (result[name] for name in sfr.PAIR)
    assert base["losses"][0] != sp["losses"][0]
    for metrics in (base, sp):
        assert len(metrics["psnr_views"]) == 5 and metrics["psnr_object"] == pytest.approx(metrics["psnr"])
        assert metrics["chamfer"] is None and 0 < metrics["psnr"] < 60
    assert (out / "renders" / "fox-toy" / "test0_gt_baseline_sp.png").is_file()
