"""Write rendered views as a Blender (``transforms_*.json``) or an SDFStudio (``meta_data.json``) dataset.

Both take cameras as OpenGL camera-to-world matrices in dataset coordinates (see
`sp_plugins.data.cameras`) and straight-alpha RGBA images in [0, 1].

Blender layout (read by nerfstudio's ``blender-data``)::

    transforms_{train,val,test}.json   {"camera_angle_x", "w", "h", "frames": [{"file_path": "./train/r_0",
                                        "rotation", "transform_matrix" (4x4 OpenGL c2w)}]}
    {train,val,test}/r_<i>.png          RGBA; the background is transparent (alpha 0)
    nb-info.json                        for nerfbaselines: its Blender loader, dataset id ``sp-scene``,
                                        the scene name and box (sp_plugins.nerfbaselines)

SDFStudio layout (read by nerfstudio's ``sdfstudio-data``), the keys of sdfstudio's format::

    meta_data.json            training frames only: nerfstudio's parser has no split, it serves
                              every frame of this file to train, val and test alike
    meta_data_{val,test}.json the held-out frames in the same format, for evaluation tools
    rgb/<split>_<i>.png       RGB composited on white
    mask/<split>_<i>.png      foreground mask (alpha >= 0.5) as 0 / 255

    top level: camera_model "OPENCV", height, width, has_mono_prior false, has_foreground_mask
    true, pairs null, worldtogt (4x4: dataset -> original mesh coordinates), scene_box {aabb,
    near, far, radius, collider_type "near_far"}: every camera ray, also a corner pixel's that
    misses the box, gets the interval [near, far], which holds the whole box for every camera
    (sdfstudio's "box" collider gives a missing ray far = near + 1e-6, and neus-facto's
    interlevel loss then divides by zero)
    per frame: rgb_path, camtoworld (4x4 OpenCV c2w), intrinsics (4x4), foreground_mask
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import imageio.v2 as imageio
import numpy as np
from jaxtyping import Float

from sp_plugins.data.cameras import opengl_to_opencv

SPLITS = ("train", "val", "test")

SplitViews = Dict[str, Tuple[Float[np.ndarray, "n 4 4"], Float[np.ndarray, "n h w 4"]]]
"""split name -> (OpenGL c2w, RGBA images)."""


def to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)


def composite_white(rgba: Float[np.ndarray, "h w 4"]) -> Float[np.ndarray, "h w 3"]:
    """Straight-alpha RGBA over a white background, as nerfstudio's ``alpha_color="white"`` does."""
    return rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2))


def write_blender(root: Path, views: SplitViews, fov_x: float, nb_info: Optional[dict] = None) -> List[Path]:
    """Write the Blender layout under `root`; returns the ``transforms_*.json`` paths.

    Each file also gives the image size (``w``, ``h``: nerfbaselines' Blender loader reads them and
    assumes 800 px without); ``nb_info`` is written as ``nb-info.json`` (which loader nerfbaselines
    uses for the folder, the dataset id, the scene box)."""
    root.mkdir(parents=True, exist_ok=True)
    if nb_info is not None:
        _write_json(root / "nb-info.json", nb_info)
    written = []
    for split, (c2w, images) in views.items():
        (root / split).mkdir(exist_ok=True)
        frames = []
        for index, (pose, image) in enumerate(zip(c2w, images)):
            imageio.imwrite(root / split / f"r_{index}.png", to_uint8(image))
            frames.append({"file_path": f"./{split}/r_{index}", "rotation": 0.0, "transform_matrix": pose.tolist()})
        path = root / f"transforms_{split}.json"
        height, width = images.shape[1:3]
        _write_json(path, {"camera_angle_x": float(fov_x), "w": int(width), "h": int(height), "frames": frames})
        written.append(path)
    return written


def sdfstudio_frames(
    root: Path, split: str, c2w: np.ndarray, images: np.ndarray, K: np.ndarray, foreground_masks: bool = True
) -> List[dict]:
    """Write one split's images (and masks) under `root`; return its ``meta_data.json`` frames."""
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    if foreground_masks:
        (root / "mask").mkdir(parents=True, exist_ok=True)
    intrinsics = np.eye(4)
    intrinsics[:3, :3] = K
    frames = []
    for index, (pose, image) in enumerate(zip(c2w, images)):
        rgb_path, mask_path = f"rgb/{split}_{index:03d}.png", f"mask/{split}_{index:03d}.png"
        imageio.imwrite(root / rgb_path, to_uint8(composite_white(image)))
        frame = {"rgb_path": rgb_path, "camtoworld": opengl_to_opencv(pose).tolist(), "intrinsics": intrinsics.tolist()}
        if foreground_masks:
            imageio.imwrite(root / mask_path, np.where(image[..., 3] >= 0.5, 255, 0).astype(np.uint8))
            frame["foreground_mask"] = mask_path
        frames.append(frame)
    return frames


def object_mask_path(layout: str, split: str, index: int) -> str:
    """Where `write_object_masks` puts view `index` of `split`, relative to the layout's root."""
    if layout == "blender":
        return f"object_mask/{split}/r_{index}.png"
    if layout == "sdfstudio":
        return f"object_mask/{split}_{index:03d}.png"
    raise ValueError(f"unknown layout {layout!r}: 'blender' or 'sdfstudio'.")


def write_object_masks(root: Path, masks: Dict[str, Float[np.ndarray, "n h w"]], layout: str) -> None:
    """Object masks for metrics (255 where a pixel is at least half object), beside a layout's images.

    They are not training masks: a DTU-like scene trains on opaque images, as DTU does without masks.
    """
    for split, split_masks in masks.items():
        for index, mask in enumerate(split_masks):
            path = root / object_mask_path(layout, split, index)
            path.parent.mkdir(parents=True, exist_ok=True)
            imageio.imwrite(path, np.where(mask >= 0.5, 255, 0).astype(np.uint8))


def write_sdfstudio(
    root: Path,
    views: SplitViews,
    K: Float[np.ndarray, "3 3"],
    width: int,
    height: int,
    aabb: Sequence[Sequence[float]],
    near: float,
    far: float,
    world_to_gt: Float[np.ndarray, "4 4"],
    foreground_masks: bool = True,
) -> List[Path]:
    """Write the SDFStudio layout under `root`; returns the meta-data paths (train first).

    Without `foreground_masks` (a DTU-like scene) the frames name no mask and training sees none.
    """
    root.mkdir(parents=True, exist_ok=True)
    written = []
    for split, (c2w, images) in views.items():
        meta = {
            "camera_model": "OPENCV",
            "height": int(height),
            "width": int(width),
            "has_mono_prior": False,
            "has_foreground_mask": bool(foreground_masks),
            "pairs": None,
            "worldtogt": np.asarray(world_to_gt).tolist(),
            "scene_box": {
                "aabb": [list(map(float, corner)) for corner in aabb],
                "near": float(near),
                "far": float(far),
                "radius": 1.0,
                "collider_type": "near_far",
            },
            "frames": sdfstudio_frames(root, split, c2w, images, K, foreground_masks),
        }
        path = root / ("meta_data.json" if split == "train" else f"meta_data_{split}.json")
        _write_json(path, meta)
        written.append(path)
    return written
