"""A Blender-format folder of your own (the ``nerf_synthetic`` layout: ``transforms_{train,val,test}.json``
and the images they name) as a nerfbaselines dataset loader, registered the nerfbaselines way (a
``dataset_loader`` spec in :mod:`sp_plugins.nerfbaselines.specs`), so ``nerfbaselines train --data DIR``
finds it as it finds a COLMAP or nerfstudio folder.

nerfbaselines 1.2.12 reads this layout only for its own benchmark (downloaded with an ``nb-info.json``
naming its loader, which takes every image as 800 px unless ``transforms_*.json`` give ``w`` and ``h``);
its format detection tries only the registered loaders, and none of its own reads this layout. Here:

- each image's size is the one its file gives (its header only), the focal length comes from
  ``camera_angle_x`` and that width, the principal point is the image centre, as nerfstudio's
  ``blender-data`` parser has them;
- poses are the files' OpenGL camera-to-world, turned to OpenCV (nerfbaselines' convention; its
  nerfstudio wrapper turns them back);
- the background is white (``background_color``): RGBA images are composited on white for training
  and evaluation, as ``blender-data``'s ``alpha_color``;
- no dataset id (a folder of yours is none of nerfbaselines' benchmarks); ``layout: blender`` in the
  metadata is what our methods' ``blender-layout`` preset applies by (nerfstudio's ``blender-data``
  parser, poses as given), so a run trains as ``ns-train ... blender-data --data DIR`` does.

Errors are one line naming the file that is missing or wrong. (``sp-scene``'s Blender folders carry an
``nb-info.json`` that names nerfbaselines' own loader; they do not come here.)
"""

from __future__ import annotations

import json
import os
from typing import List, Tuple

__all__ = ["LAYOUT", "LAYOUT_KEY", "SPLITS", "load_blender_folder"]

SPLITS = ("train", "val", "test")
LAYOUT_KEY, LAYOUT = "layout", "blender"
"""The metadata entry our ``blender-layout`` preset applies by."""


def _transforms(path: str, split: str) -> dict:
    """``transforms_{split}.json``, once the folder has the three that make the layout."""
    missing = [f"transforms_{s}.json" for s in SPLITS if not os.path.isfile(os.path.join(path, f"transforms_{s}.json"))]
    if missing:
        raise FileNotFoundError(f"{path} is no Blender-format folder: {', '.join(missing)} missing "
                                "(the layout has transforms_train.json, transforms_val.json and transforms_test.json)")
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: a Blender-format folder has {', '.join(SPLITS)}")
    file = os.path.join(path, f"transforms_{split}.json")
    try:
        with open(file, encoding="utf8") as f:
            meta = json.load(f)
    except ValueError as err:
        raise ValueError(f"{file} is not JSON ({err})") from None
    if "camera_angle_x" not in meta or not meta.get("frames"):
        raise ValueError(f"{file} needs camera_angle_x and a non-empty frames list (the Blender layout's keys)")
    return meta


def _image_path(path: str, file_path: str) -> str:
    """A frame's image: ``file_path`` as written, or with ``.png`` added (as ``blender-data`` reads it)."""
    name = os.path.normpath(os.path.join(path, file_path))
    if os.path.isfile(name):
        return name
    if os.path.isfile(name + ".png"):
        return name + ".png"
    raise FileNotFoundError(f"{name}.png is missing: a frame of the Blender-format folder {path} names it")


def _image_sizes(paths: List[str]) -> List[Tuple[int, int]]:
    """Width and height of each image, from its header (nerfbaselines loads the pixels later)."""
    from PIL import Image

    sizes = []
    for name in paths:
        with Image.open(name) as image:
            sizes.append(image.size)
    return sizes


def pinhole_cameras(poses, intrinsics, image_sizes, nears_fars=None):
    """nerfbaselines cameras of ``len(poses)`` pinhole frames without distortion (our loaders' frames)."""
    import numpy as np
    from nerfbaselines import camera_model_to_int, new_cameras

    n = len(poses)
    extra = {} if nears_fars is None else {"nears_fars": nears_fars}
    return new_cameras(poses=poses, intrinsics=intrinsics, camera_models=np.full(n, camera_model_to_int("pinhole"), dtype=np.int32),
                       distortion_parameters=np.zeros((n, 0), dtype=np.float32), image_sizes=image_sizes, **extra)


def load_blender_folder(path: str, split: str, **kwargs):
    """The ``split`` of the Blender-format folder at ``path`` (pinhole, true image sizes, white background)."""
    import numpy as np
    from nerfbaselines import new_dataset

    del kwargs
    meta = _transforms(path, split)
    frames = meta["frames"]
    image_paths = [_image_path(path, str(frame["file_path"])) for frame in frames]
    sizes = np.array(_image_sizes(image_paths), dtype=np.int32)
    c2w = np.array([np.asarray(frame["transform_matrix"], dtype=np.float32)[:3, :4] for frame in frames])
    c2w[..., 0:3, 1:3] *= -1  # OpenGL -> OpenCV camera axes
    width, height = sizes[:, 0].astype(np.float32), sizes[:, 1].astype(np.float32)
    focal = 0.5 * width / np.tan(0.5 * float(meta["camera_angle_x"]))
    intrinsics = np.stack([focal, focal, 0.5 * width, 0.5 * height], -1).astype(np.float32)
    return new_dataset(
        cameras=pinhole_cameras(c2w, intrinsics, sizes),
        image_paths_root=path,
        image_paths=image_paths,
        mask_paths=None,
        metadata={"color_space": "srgb", "type": "object-centric", "evaluation_protocol": "default",
                  "background_color": np.array([255, 255, 255], dtype=np.uint8), LAYOUT_KEY: LAYOUT},
    )
