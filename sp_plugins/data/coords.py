"""From dataset coordinates (``gt_mesh.ply``) to the coordinates a nerfstudio model trains in.

nerfstudio's dataparsers may move the world: ``x_nerfstudio = s * (T @ [x_dataset, 1])``.

- ``blender-data``: T is the identity and s is its ``scale_factor`` (``dataparser_scale``).
- ``sdfstudio-data``: s = 1 and T is ``metadata["transform"]`` from ``auto_orient`` (identity for
  scenes from `make_scene`, whose training cameras have a mean up vector of exactly +Z). Note that
  nerfstudio's saved ``dataparser_transforms.json`` does *not* record this transform.

Reconstructed meshes exported by a nerfstudio model are in nerfstudio coordinates: compare them
with `load_gt_mesh(scene, dataparser_outputs)` or map them back with the inverse of
`dataset_to_nerfstudio`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np
import trimesh
from jaxtyping import Float

from sp_plugins.data.scene import GT_MESH_FILE, SCENE_FILE


def scene_root(path: Union[str, Path]) -> Path:
    """The scene directory for a scene root or one of its layout directories (``.../blender``)."""
    path = Path(path).expanduser()
    for candidate in (path, path.parent):
        if (candidate / SCENE_FILE).is_file():
            return candidate
    raise ValueError(f"no {SCENE_FILE} in {path} or its parent: is it a scene written by make_scene / sp-scene?")


def read_scene(path: Union[str, Path]) -> dict:
    """The ``scene.json`` of a scene (root or layout directory)."""
    return json.loads((scene_root(path) / SCENE_FILE).read_text())


def dataset_to_nerfstudio(source: Any) -> Float[np.ndarray, "4 4"]:
    """4x4 map from dataset to nerfstudio coordinates.

    `source` is a nerfstudio ``DataparserOutputs`` (of the training split) or the path of a run's
    ``dataparser_transforms.json`` (``{"transform": 3x4, "scale": s}``).
    """
    matrix = np.eye(4)
    if isinstance(source, (str, Path)):
        saved = json.loads(Path(source).read_text())
        matrix[:3, :] = np.asarray(saved["transform"], dtype=np.float64)
        scale = float(saved["scale"])
    else:
        transform = (getattr(source, "metadata", None) or {}).get("transform")
        if transform is None:
            transform = source.dataparser_transform
        matrix[:3, :] = np.asarray(transform, dtype=np.float64)[:3, :4]
        scale = float(source.dataparser_scale)
    return np.diag([scale, scale, scale, 1.0]) @ matrix


def load_gt_mesh(path: Union[str, Path], dataparser_outputs: Optional[Any] = None) -> trimesh.Trimesh:
    """The scene's true mesh, in dataset coordinates or, given `dataparser_outputs`, in nerfstudio's."""
    mesh = trimesh.load(scene_root(path) / GT_MESH_FILE, force="mesh", process=False)
    if dataparser_outputs is not None:
        mesh.apply_transform(dataset_to_nerfstudio(dataparser_outputs))
    return mesh
