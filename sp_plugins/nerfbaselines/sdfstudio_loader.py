"""Our SDFStudio layout (``meta_data.json``, what ``sp-scene`` writes under ``sdfstudio/``) as a
nerfbaselines dataset loader, registered the nerfbaselines way (a ``dataset_loader`` spec in
:mod:`sp_plugins.nerfbaselines.specs`), so ``--data my-scene/sdfstudio`` is detected like a COLMAP
or nerfstudio folder. Splits: ``meta_data.json`` is the training split, ``meta_data_test.json`` the
test split (nerfbaselines asks for ``train`` and ``test``). The metadata carries the layout's
``scene_box`` (its ``aabb``), which our methods use (:mod:`sp_plugins.nerfbaselines.scene_box`).
"""

from __future__ import annotations

import json
import os

from sp_plugins.nerfbaselines.blender_loader import pinhole_cameras

__all__ = ["load_sdfstudio_dataset", "refuse_download"]

def _meta_path(path: str, split: str) -> str:
    return os.path.join(path, "meta_data.json" if split == "train" else f"meta_data_{split}.json")


def _scene_of(path: str) -> dict:
    """Dataset id and scene name of a folder sp-scene wrote (its ``scene.json`` one level up)."""
    try:
        with open(os.path.join(path, os.pardir, "scene.json"), encoding="utf8") as f:
            scene = json.load(f)
    except (OSError, ValueError):
        return {}
    if scene.get("format") != "sp-plugins synthetic scene":
        return {}
    from sp_plugins.nerfbaselines.specs import SP_SCENE  # defers torch and nerfbaselines: a loader module stays light

    return {"id": SP_SCENE, "evaluation_protocol": SP_SCENE, "scene": os.path.splitext(os.path.basename(str(scene.get("source", "scene"))))[0]}


def load_sdfstudio_dataset(path: str, split: str, **kwargs):
    """The ``split`` of the SDFStudio layout at ``path`` (OpenCV camera-to-world, pinhole)."""
    import numpy as np
    from nerfbaselines import new_dataset

    del kwargs
    train_meta = os.path.join(path, "meta_data.json")
    if not os.path.isfile(train_meta):
        raise FileNotFoundError(f"no meta_data.json in {path}")
    meta_path = _meta_path(path, split)
    if not os.path.isfile(meta_path):
        raise FileNotFoundError(f"{os.path.basename(meta_path)} is missing in {path} (the SDFStudio layout's {split} split)")
    with open(meta_path, encoding="utf8") as f:
        meta = json.load(f)
    frames = meta["frames"]
    c2w = np.array([frame["camtoworld"] for frame in frames], dtype=np.float32)[:, :3, :4]
    K = np.array([frame["intrinsics"] for frame in frames], dtype=np.float32)
    intrinsics = np.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]], -1)
    n = len(frames)
    box = meta.get("scene_box", {})
    near, far = float(box.get("near", 0.05)), float(box.get("far", 100.0))
    metadata = {"color_space": "srgb", "type": "object-centric", "evaluation_protocol": "default",
                "background_color": np.array([255, 255, 255], dtype=np.uint8), **_scene_of(path)}
    if "aabb" in box:
        metadata["scene_box"] = [[float(v) for v in corner] for corner in box["aabb"]]
    return new_dataset(
        cameras=pinhole_cameras(c2w, intrinsics, np.array([[meta["width"], meta["height"]]] * n, dtype=np.int32),
                                np.array([[near, far]] * n, dtype=np.float32)),
        image_paths_root=path,
        image_paths=[os.path.join(path, frame["rgb_path"]) for frame in frames],
        mask_paths=None,
        metadata=metadata,
    )


def refuse_download(path: str, output: str) -> None:
    """``external://sp-scene/...``: there is nothing to download; sp-scene makes the scene here."""
    del output
    raise RuntimeError(f"{path}: sp-scene datasets are made locally, not downloaded: sp-scene spot my-scene, "
                       "then --data my-scene/blender (or my-scene/sdfstudio)")
