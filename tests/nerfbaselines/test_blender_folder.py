"""A Blender-format folder of one's own (the ``nerf_synthetic`` layout: ``transforms_{train,val,test}.json``
without ``w`` / ``h``, no ``nb-info.json``, images not 800 px) through nerfbaselines' own format
detection: our ``blender-layout`` loader finds it, with the true image size and intrinsics, and our
methods' preset puts it on nerfstudio's ``blender-data`` parser. (Training on one runs in
test_nerfbaselines.py.)"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

SIZE = (40, 24)  # width, height: not square, so a swapped width and height shows
ANGLE = 0.7  # camera_angle_x
COUNTS = {"train": 4, "val": 1, "test": 2}


def pose(index: int) -> np.ndarray:
    """An OpenGL camera-to-world looking at the origin from radius 4."""
    theta = 2 * math.pi * index / 5
    eye = np.array([4 * math.cos(theta), 4 * math.sin(theta), 1.0])
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(back, right), back], -1)
    c2w[:3, 3] = eye
    return c2w


def write_folder(root: Path) -> Path:
    """A tiny Blender-format folder as nerf_synthetic has it: RGBA PNGs, frames without extension."""
    from PIL import Image

    rng = np.random.default_rng(0)
    for split, count in COUNTS.items():
        (root / split).mkdir(parents=True)
        frames = []
        for i in range(count):
            Image.fromarray(rng.integers(0, 256, (SIZE[1], SIZE[0], 4), dtype=np.uint8), "RGBA").save(root / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0, "transform_matrix": pose(i).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": ANGLE, "frames": frames}))
    return root


@pytest.fixture
def folder(tmp_path) -> Path:
    return write_folder(tmp_path / "my-object")


def test_format_detection_finds_the_folder_with_its_true_size(folder):
    from nerfbaselines.datasets import load_dataset

    for split in ("train", "test"):
        dataset = load_dataset(str(folder), split=split)  # no loader named: nerfbaselines tries every registered one
        n = COUNTS[split]
        assert len(dataset["images"]) == n and dataset["images"][0].shape == (SIZE[1], SIZE[0], 4)
        cameras = dataset["cameras"]
        assert cameras.image_sizes.tolist() == [list(SIZE)] * n
        focal = 0.5 * SIZE[0] / math.tan(0.5 * ANGLE)  # nerfstudio's blender-data: from the width, fx = fy
        np.testing.assert_allclose(cameras.intrinsics, [[focal, focal, SIZE[0] / 2, SIZE[1] / 2]] * n, rtol=1e-6)
        opencv = np.stack([pose(i) for i in range(n)])[:, :3, :4] * np.array([1, -1, -1, 1])
        np.testing.assert_allclose(cameras.poses, opencv, atol=1e-6)
        assert dataset["metadata"]["background_color"].tolist() == [255, 255, 255]
        assert dataset["metadata"]["layout"] == "blender" and "id" not in dataset["metadata"]


def test_an_nb_info_naming_our_loader_loads_the_same(folder):
    from nerfbaselines.datasets import load_dataset

    (folder / "nb-info.json").write_text(json.dumps({"loader": "blender-layout", "scene": "my-object"}))
    dataset = load_dataset(str(folder), split="train", load_features=False)
    assert dataset["cameras"].image_sizes.tolist() == [list(SIZE)] * COUNTS["train"]
    assert dataset["metadata"]["scene"] == "my-object"


def test_our_methods_train_it_on_blender_data_as_ns_train_does(folder):
    import nerfbaselines
    from nerfbaselines.datasets import load_dataset
    from nerfbaselines.training import get_presets_and_config_overrides

    from sp_plugins.nerfbaselines.specs import ENTRIES

    metadata = load_dataset(str(folder), split="train", load_features=False)["metadata"]
    for method_id in ENTRIES:
        presets, overrides = get_presets_and_config_overrides(nerfbaselines.get_method_spec(method_id), metadata)
        assert presets == {"blender-layout"} and overrides == {"pipeline.datamanager.dataparser": "blender-data"}, method_id


def test_what_is_not_the_layout_is_one_line_naming_the_file(folder):
    from sp_plugins.nerfbaselines.blender_loader import load_blender_folder

    (folder / "transforms_val.json").unlink()
    with pytest.raises(FileNotFoundError) as err:
        load_blender_folder(str(folder), "train")
    assert "\n" not in str(err.value) and "transforms_val.json missing" in str(err.value)
    write_folder(folder.parent / "other")
    (folder.parent / "other" / "test" / "r_1.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"test/r_1.png is missing: a frame of the Blender-format folder"):
        load_blender_folder(str(folder.parent / "other"), "test")
