"""Where the studies' scenes come from: meshes by file or name, scenes rendered once per setting, real captures.

Shared data (test meshes, the fox capture) is looked for next to the checkout, in
``../shared/data`` (``meshes/``, ``real/fox``), or in ``SP_SHARED_DATA``; ``SP_FOX_CAPTURE`` names
another fox folder, and the studies that train on a capture take it as an argument too. Nothing here
names a machine path.

A mesh name resolves to the shared file when there is one (:func:`mesh_source`): ``spot`` in the
DTU-like studies is ``../shared/data/meshes/spot.ply`` (Y-up, stood on z: Spot sits on its haunches,
nose up), not the bundled ``spot`` (the same mesh turned Z-up). A scene rendered once is reused only
for the mesh it was rendered from (:func:`rendered`), so the two never mix.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Dict, Tuple

SHARED_DATA = Path(os.environ.get("SP_SHARED_DATA", Path(__file__).resolve().parents[2].parent / "shared" / "data"))
SHARED_MESHES = SHARED_DATA / "meshes"
FOX = Path(os.environ.get("SP_FOX_CAPTURE", SHARED_DATA / "real" / "fox"))
"""The instant-ngp fox (``transforms.json``, COLMAP poses): ``SP_FOX_CAPTURE`` or ``../shared/data/real/fox``."""
REAL: Dict[str, Path] = {"fox": FOX}
"""Real captures a study's scene may name: no true mesh and no object mask."""


def is_real(mesh: str) -> bool:
    return mesh in REAL


def mesh_source(mesh: str) -> str:
    """A file as given; else a shared test mesh by stem (``homer``); else a bundled or primitive name."""
    shared = SHARED_MESHES / f"{mesh}.ply"
    return str(shared) if not Path(mesh).is_file() and shared.is_file() else mesh


def capture(folder: Path, label: str = "", hint: str = "set SP_FOX_CAPTURE to its folder") -> Path:
    """``folder`` if it holds a capture (``transforms.json``), else a one-line exit naming where it was looked for."""
    folder = Path(folder)
    if not (folder / "transforms.json").is_file():
        raise SystemExit(f"{label or folder}: no capture at {folder} (transforms.json); {hint}")
    return folder


def synthetic(mesh: str, root: Path, *, views: int, test_views: int, resolution, n_val: int = 2,
              layout: str = "blender") -> Path:
    """An object on white rendered once into ``root`` (:func:`sp_plugins.data.make_scene`); returns ``root``."""
    from sp_plugins.data import make_scene

    if not (root / "scene.json").is_file():
        make_scene(mesh, root, n_train=views, n_val=n_val, n_test=test_views, resolution=resolution,
                   layouts=(layout,), seed=0, overwrite=True)
    return root


def rendered(mesh: str, out: Path, *, up_axis: str = "z", dtu_like: bool = True, views: int = 49, test_views: int = 3,
             resolution: Tuple[int, int] = (96, 72), layout: str = "blender") -> Path:
    """A scene rendered once under ``out/scenes`` and shared by every setting that agrees on it: the
    DTU-like scene (``sp-scene --dtu-like``: ground, backdrop, a frontal cap of cameras) by default."""
    from sp_plugins.data import make_scene

    key = f"{Path(mesh).stem}_{'dtu' if dtu_like else 'white'}_{views}v_{resolution[0]}x{resolution[1]}"
    root = out / "scenes" / key
    source = mesh_source(mesh)
    if (root / "scene.json").is_file():
        made_from = json.loads((root / "scene.json").read_text()).get("source")
        if made_from != source:
            raise SystemExit(f"{root}: rendered from {made_from}, not {source} (../shared present in one run and "
                             f"not in the other? SP_SHARED_DATA names it); remove that folder to render it again")
    else:
        logging.info("rendering scene %s", key)
        make_scene(source, root, up_axis=up_axis, n_train=views, n_val=1, n_test=test_views,
                   resolution=resolution, layouts=(layout,), seed=0, dtu_like=dtu_like, overwrite=True)
    return root


def object_mask_paths(data: Path, image_filenames) -> list:
    """The object mask of each test image of a DTU-like scene's Blender layout (same file name)."""
    masks = [data / "object_mask" / "test" / Path(f).name for f in image_filenames]
    missing = [m for m in masks if not m.is_file()]
    if missing:
        raise FileNotFoundError(f"no object mask {missing[0]}: render the scene with sp-scene --dtu-like")
    return masks
