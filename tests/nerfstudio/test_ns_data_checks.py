"""Bad input to the SDF methods fails early with the file and the expectation in the message."""

from __future__ import annotations

import contextlib
import json
import shutil

import pytest
import torch
from PIL import Image

from sp_plugins.nerfstudio.components.data_checks import ray_hits_box
from sp_plugins.nerfstudio.components.datamanagers import SurfaceDataset


def _setup(config):
    return config.pipeline.datamanager.setup(device="cpu", test_mode="val")


@pytest.fixture
def scene_copy(tiny_scene, tmp_path):
    target = tmp_path / "scene"
    shutil.copytree(tiny_scene, target)
    return target


def test_missing_folder(tiny_scene, tiny_config, tmp_path):
    config = tiny_config("sp-neus", tiny_scene, tmp_path, layout="sdfstudio")
    config.pipeline.datamanager.data = tmp_path / "nowhere"
    with pytest.raises(ValueError, match=r"nowhere: data folder not found.*SDFStudio layout"):
        _setup(config)


def test_wrong_layout_names_the_missing_file(tiny_scene, tiny_config, tmp_path):
    config = tiny_config("sp-neus", tiny_scene, tmp_path, layout="sdfstudio")
    config.pipeline.datamanager.data = tiny_scene / "blender"  # a Blender scene given to sdfstudio-data
    with pytest.raises(ValueError, match=r"blender/meta_data.json: file not found; expected an SDFStudio scene.*"
                       r"holds transforms_train.json, so it reads with blender-data --data .*blender$"):
        _setup(config)
    config = tiny_config("sp-neus", tiny_scene, tmp_path, layout="blender")
    config.pipeline.datamanager.data = tiny_scene / "sdfstudio"
    with pytest.raises(ValueError, match=r"transforms_train.json: file not found; expected a Blender scene.*"
                       r"holds meta_data.json, so it reads with sdfstudio-data --data .*sdfstudio$"):
        _setup(config)


def test_scene_root_points_at_its_layout_folders(tiny_scene, tiny_config, tmp_path):
    config = tiny_config("sp-neus", tiny_scene, tmp_path, layout="blender")
    config.pipeline.datamanager.data = tiny_scene  # the root that sp-scene wrote, not a layout folder
    with pytest.raises(ValueError, match=r"sub-folders hold scenes: blender-data --data .*blender, sdfstudio-data --data .*sdfstudio"):
        _setup(config)


def test_missing_image_is_named(scene_copy, tiny_config, tmp_path):
    meta = json.loads((scene_copy / "sdfstudio" / "meta_data.json").read_text())
    victim = scene_copy / "sdfstudio" / meta["frames"][3]["rgb_path"]
    victim.unlink()
    config = tiny_config("sp-neus", scene_copy, tmp_path, layout="sdfstudio")
    with pytest.raises(ValueError, match=rf"{victim.name}: image not found \(frame 3 of meta_data.json\)"):
        _setup(config)


@pytest.mark.parametrize("layout", ["sdfstudio", "blender"])
def test_mixed_image_sizes_are_named(layout, scene_copy, tiny_config, tmp_path):
    if layout == "sdfstudio":
        meta = json.loads((scene_copy / "sdfstudio" / "meta_data.json").read_text())
        victim = scene_copy / "sdfstudio" / meta["frames"][2]["rgb_path"]
    else:
        meta = json.loads((scene_copy / "blender" / "transforms_train.json").read_text())
        victim = scene_copy / "blender" / (meta["frames"][2]["file_path"].replace("./", "") + ".png")
    with Image.open(victim) as im:
        im.resize((24, 20)).save(victim)
    config = tiny_config("sp-neus-hashgrid", scene_copy, tmp_path, layout=layout)
    with pytest.raises(ValueError, match=rf"{victim.name}: image is 24x20 pixels, expected 32x32"):
        _setup(config)


@contextlib.contextmanager
def _edited(path):
    """A scene's JSON file, to change in place: written back when the block ends."""
    meta = json.loads(path.read_text())
    yield meta
    path.write_text(json.dumps(meta))


def test_scene_box_that_misses_the_cameras_look_at_points(scene_copy, tiny_config, tmp_path):
    with _edited(scene_copy / "sdfstudio" / "meta_data.json") as meta:
        meta["scene_box"]["aabb"] = [[5.0, 5.0, 5.0], [7.0, 7.0, 7.0]]  # wrong units / frame
    config = tiny_config("sp-neus", scene_copy, tmp_path, layout="sdfstudio")
    with pytest.raises(ValueError, match=r"rgb/.*: its camera .* looks past the scene box \(scene_box.aabb of .*meta_data.json\) .* cameras do"):
        _setup(config)


def test_blender_cameras_outside_the_fixed_box_are_named(scene_copy, tiny_config, tmp_path):
    for split in ("train", "val"):
        with _edited(scene_copy / "blender" / f"transforms_{split}.json") as meta:
            for frame in meta["frames"]:
                frame["transform_matrix"][0][3] += 10.0  # poses in other units / another origin
    config = tiny_config("sp-neus", scene_copy, tmp_path, layout="blender")
    with pytest.raises(ValueError, match=r"r_0.png: its camera .* looks past the Blender scene box .*--scale-factor"):
        _setup(config)


def test_good_scene_passes_and_surface_dataset_needs_no_depth(tiny_scene, tiny_config, tmp_path):
    for layout in ("sdfstudio", "blender"):
        dm = _setup(tiny_config("sp-neus", tiny_scene, tmp_path / layout, layout=layout))
        assert isinstance(dm.train_dataset, SurfaceDataset)
        item = dm.train_dataset[0]
        assert item["image"].shape == (32, 32, 3) and "depth" not in item


def test_ray_box_slab_test():
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    origins = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 4.0], [0.0, 3.0, 4.0], [0.0, 0.0, 0.0]])
    dirs = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    assert ray_hits_box(origins, dirs, box).tolist() == [True, False, False, True]


def test_nerfstudio_data_capture_passes_and_a_damaged_image_is_named(tmp_path):
    """nerfstudio-data (ns-train's default dataparser) is checked before the run folder is written:
    a capture folder or its transforms.json passes; a damaged image it names is refused by name (under
    a worker-process data manager it hung the run); a missing one is left to the host (it may read it
    from images_N)."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from sp_plugins.adapter.errors import InputError
    from sp_plugins.nerfstudio.components.data_checks import check_data_layout

    (tmp_path / "images").mkdir()
    for name in ("a", "b"):
        Image.new("RGB", (8, 8)).save(tmp_path / "images" / f"{name}.png")
    frames = [{"file_path": f"images/{n}.png", "transform_matrix": torch.eye(4).tolist()} for n in ("a", "b", "gone")]
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    parser = NerfstudioDataParserConfig()
    check_data_layout(parser, tmp_path)
    check_data_layout(parser, tmp_path / "transforms.json")
    (tmp_path / "blender").mkdir()  # a Blender scene given to nerfstudio-data
    (tmp_path / "blender" / "transforms_train.json").write_text("{}")
    data = (tmp_path / "images" / "b.png").read_bytes()
    (tmp_path / "images" / "b.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"images/b.png: cannot be read as an image .*frame 1 of transforms.json"):
        check_data_layout(parser, tmp_path)
    with pytest.raises(InputError, match=r"transforms.json: file not found; expected a nerfstudio capture.*so it reads with "
                       r"blender-data --data"):
        check_data_layout(parser, tmp_path / "blender")
