"""Training on only N of the training views: any method, any dataparser."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig
from tests.helpers.ns_configs import run_recording, tiny_radiance_config

from sp_plugins.nerfstudio.components.datamanagers import CheckedDataManagerConfig
from sp_plugins.nerfstudio.components.views import farthest_views, select_views, subset_views, view_indices


@pytest.fixture(scope="module")
def blender_outputs(tiny_scene):
    return BlenderDataParserConfig(data=tiny_scene / "blender").setup().get_dataparser_outputs("train")


def test_spread_selection_is_farthest_point_order():
    centres = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [10.0, 0, 0], [5.0, 0, 0], [9.0, 0, 0]])
    assert farthest_views(centres, 3) == [0, 2, 3]


def test_view_indices_kinds_and_errors(blender_outputs):
    total = len(blender_outputs.image_filenames)
    assert view_indices(blender_outputs, 3, "first") == [0, 1, 2]
    spread = view_indices(blender_outputs, 4, "spread")
    assert len(set(spread)) == 4 and 0 in spread
    # spread views are farther apart than the first ones (the cameras of make_scene are in random order)
    centres = blender_outputs.cameras.camera_to_worlds[:, :3, 3]

    def min_gap(ids):
        c = centres[ids]
        d = torch.cdist(c, c) + torch.eye(len(ids)) * 1e9
        return float(d.min())

    assert min_gap(spread) >= min_gap(view_indices(blender_outputs, 4, "first"))
    r1, r2 = view_indices(blender_outputs, 3, "random", seed=1), view_indices(blender_outputs, 3, "random", seed=1)
    assert r1 == r2 and len(set(r1)) == 3
    assert view_indices(blender_outputs, total, "spread") == list(range(total))
    with pytest.raises(ValueError, match=f"only {total} views"):
        view_indices(blender_outputs, total + 1)
    with pytest.raises(ValueError, match=">= 1"):
        view_indices(blender_outputs, 0)
    with pytest.raises(ValueError, match="train_view_selection"):
        view_indices(blender_outputs, 2, "best")  # type: ignore[arg-type]


def test_random_selection_is_a_seeded_sorted_subset_of_the_size_asked_for(blender_outputs):
    """``random`` keeps ``n`` distinct views, sorted, drawn from the whole training split: the same seed gives the
    same views whatever the global RNG's state (and leaves that state alone), other seeds give other subsets,
    unlike ``first`` and ``spread``, which do not depend on the seed, and over seeds every view can be drawn."""
    total = len(blender_outputs.image_filenames)
    with torch.random.fork_rng(devices=[]):  # the global state this test sets is not left to the others
        torch.manual_seed(123)
        state = torch.get_rng_state()
        chosen = {seed: view_indices(blender_outputs, 3, "random", seed=seed) for seed in range(40)}
        assert torch.equal(torch.get_rng_state(), state)  # the global generator is not drawn from
        for seed, ids in chosen.items():
            assert len(ids) == 3 and len(set(ids)) == 3 and ids == sorted(ids) and 0 <= ids[0] and ids[-1] < total, (seed, ids)
            torch.manual_seed(seed + 1000)  # another global state: the same views
            assert view_indices(blender_outputs, 3, "random", seed=seed) == ids
    subsets = {tuple(ids) for ids in chosen.values()}
    assert len(subsets) > 10  # 56 subsets of 3 of 8 views: the seed decides
    assert set().union(*subsets) == set(range(total))  # no view left out of every draw
    for other in ("first", "spread"):
        fixed = view_indices(blender_outputs, 3, other)
        assert all(view_indices(blender_outputs, 3, other, seed=seed) == fixed for seed in (0, 1, 7))
        assert subsets != {tuple(fixed)}
    assert view_indices(blender_outputs, total, "random", seed=5) == list(range(total))


def test_the_data_manager_trains_on_the_random_views_of_its_seed(tiny_scene):
    """``--pipeline.datamanager.train-view-selection random --pipeline.datamanager.train-view-seed S`` trains on
    the views ``view_indices`` draws with seed S; another seed, other views."""
    parser = BlenderDataParserConfig(data=tiny_scene / "blender")
    outputs = parser.setup().get_dataparser_outputs("train")
    a = view_indices(outputs, 3, "random", seed=0)
    b_seed = next(seed for seed in range(1, 50) if view_indices(outputs, 3, "random", seed=seed) != a)
    for seed in (0, b_seed):
        config = CheckedDataManagerConfig(dataparser=BlenderDataParserConfig(data=tiny_scene / "blender"), train_views=3,
                                          train_view_selection="random", train_view_seed=seed)
        dm = config.setup(device="cpu", test_mode="val")
        want = [outputs.image_filenames[i].name for i in view_indices(outputs, 3, "random", seed=seed)]
        assert [p.name for p in dm.train_dataparser_outputs.image_filenames] == want, seed


def test_subset_keeps_images_cameras_and_per_image_metadata_together(tiny_scene):
    outputs = SDFStudioDataParserConfig(data=tiny_scene / "sdfstudio").setup().get_dataparser_outputs("train")
    outputs.metadata["depth_filenames"] = [f"d{i}" for i in range(len(outputs.image_filenames))]
    sub = subset_views(outputs, [1, 5, 6])
    assert [p.name for p in sub.image_filenames] == [outputs.image_filenames[i].name for i in (1, 5, 6)]
    assert torch.equal(sub.cameras.camera_to_worlds, outputs.cameras.camera_to_worlds[[1, 5, 6]])
    assert sub.metadata["depth_filenames"] == ["d1", "d5", "d6"]
    if isinstance(outputs.metadata.get("camera_to_worlds"), torch.Tensor):
        assert sub.metadata["camera_to_worlds"].shape[0] == 3
    assert torch.equal(sub.scene_box.aabb, outputs.scene_box.aabb)
    assert select_views(outputs, -1) is outputs
    with pytest.raises(ValueError, match="distinct"):
        subset_views(outputs, [1, 1])


def test_data_manager_trains_on_n_views_and_evaluates_on_all(tiny_scene):
    config = CheckedDataManagerConfig(dataparser=BlenderDataParserConfig(data=tiny_scene / "blender"), train_views=3,
                                      train_view_selection="first")
    dm = config.setup(device="cpu", test_mode="val")
    assert len(dm.train_dataset) == 3 and len(dm.train_dataparser_outputs.image_filenames) == 3
    full = BlenderDataParserConfig(data=tiny_scene / "blender").setup()
    assert len(dm.eval_dataset) == len(full.get_dataparser_outputs("val").image_filenames)
    # every training ray comes from one of the 3 cameras
    _, batch = dm.next_train(0)
    assert set(batch["indices"][:, 0].tolist()) <= {0, 1, 2}
    with pytest.raises(ValueError, match="only 8 views"):
        CheckedDataManagerConfig(dataparser=BlenderDataParserConfig(data=tiny_scene / "blender"), train_views=9).setup(
            device="cpu", test_mode="val")


@pytest.mark.parametrize("name", ["sp-mipnerf", "sp-relu-field"])
def test_a_method_trains_on_a_view_subset(name, tiny_scene, tmp_path):
    config = tiny_radiance_config(name, tiny_scene, tmp_path, steps=2)
    config.pipeline.datamanager.train_views = 2
    trainer, record = run_recording(config)
    assert trainer.pipeline.datamanager.train_dataset.cameras.shape == (2,)
    assert trainer.pipeline.model.num_train_data == 2
    assert all(math.isfinite(loss) for loss, _, _ in record)
