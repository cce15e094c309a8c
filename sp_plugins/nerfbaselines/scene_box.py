"""The scene box our methods get under nerfbaselines: the dataset's, where it has one.

nerfbaselines' nerfstudio wrapper gives every model a fixed box (+-1.5 for nerfstudio's Blender parser,
+-1 for its COLMAP / nerfstudio parsers, whose poses it re-centres and scales). A dataset that knows
its box says so in its metadata (``scene_box``: ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``; our
SDFStudio loader reads it from ``meta_data.json``, ``sp-scene`` writes it in the Blender layout's
``nb-info.json``). That box is in the dataset's own coordinates, so it is used where the poses stay
as given (nerfstudio's Blender parser): SDF methods (whose surface lives in the box) are put on that
parser when the dataset has a box; radiance methods keep the box nerfstudio's parser gives, as under
``ns-train``. The box is saved beside the checkpoint, so ``render`` rebuilds the same model.
"""

from __future__ import annotations

import json
import os
from typing import Any, List, Optional

__all__ = ["FILE", "dataset_box", "load", "save", "scene_box_class"]

FILE = "sp-scene-box.json"


def dataset_box(dataset: Optional[dict]) -> Optional[List[List[float]]]:
    """The box in a nerfbaselines dataset's metadata (None when it has none)."""
    if dataset is None:
        return None
    box = dataset.get("metadata", {}).get("scene_box")
    if box is None:
        return None
    box = [[float(v) for v in corner] for corner in box]
    if len(box) != 2 or any(len(c) != 3 for c in box) or any(lo >= hi for lo, hi in zip(*box)):
        raise ValueError(f"the dataset's scene_box {box} is not [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max")
    return box


def save(folder: str, box: Optional[List[List[float]]]) -> None:
    if box is not None:
        with open(os.path.join(folder, FILE), "w", encoding="utf8") as f:
            json.dump({"aabb": box}, f)


def load(folder: Optional[str]) -> Optional[List[List[float]]]:
    path = os.path.join(folder, FILE) if folder else None
    if path is None or not os.path.exists(path):
        return None
    with open(path, encoding="utf8") as f:
        return json.load(f)["aabb"]


def scene_box_class(parser_cls: Any, box: List[List[float]]) -> Any:
    """A subclass of nerfbaselines' data parser whose ``scene_box`` is ``box``."""
    import torch
    from nerfstudio.data.scene_box import SceneBox

    class DatasetBoxParser(parser_cls):
        @property
        def scene_box(self):
            return SceneBox(aabb=torch.tensor(box, dtype=torch.float32))

    return DatasetBoxParser
