"""Checks of a nerfstudio run's data before training, each failure an :class:`InputError` naming the file and what was
expected (one line under ``ns-train``): the folder and its layout (``sdfstudio-data``, ``blender-data``,
``nerfstudio-data``, a COLMAP model where another layout was asked for), the images readable and of their cameras'
sizes, and every camera looking into the scene box. Used by our data managers
(:mod:`~sp_plugins.nerfstudio.components.datamanagers`) and, before the run folder is written, by ``ns-train``'s
checked run config (:mod:`~sp_plugins.nerfstudio.components.trainer`).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple

import torch
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig

from sp_plugins.adapter.errors import InputError


# -- layout -----------------------------------------------------------------------------------


_LAYOUT_MARKERS = {"sdfstudio-data": "meta_data.json", "blender-data": "transforms_train.json"}


_COLMAP_MODELS = ("sparse/0", "colmap/sparse/0", "sparse", "colmap/sparse")


def _colmap_model(data: Path) -> Optional[Path]:
    """The COLMAP reconstruction (cameras.bin / cameras.txt) in ``data`` or where nerfstudio keeps one."""
    for sub in ("", *_COLMAP_MODELS):
        folder = data / sub if sub else data
        if (folder / "cameras.bin").is_file() or (folder / "cameras.txt").is_file():
            return folder
    return None


def _layout_hint(data: Path) -> str:
    """What ``data`` looks like instead: the other layout, a nerfstudio or COLMAP capture, or a scene
    root with layout sub-folders."""
    found = [parser for parser, marker in _LAYOUT_MARKERS.items() if (data / marker).is_file()]
    if found:
        return f"; this folder holds {_LAYOUT_MARKERS[found[0]]}, so it reads with {found[0]} --data {data}"
    if (data / "transforms.json").is_file():
        return (f"; this folder holds transforms.json, a nerfstudio capture: it reads with nerfstudio-data --data {data} "
                "(sp-nerfacto's default), or for the SDF methods after conversion to the SDFStudio layout")
    colmap = _colmap_model(data)
    if colmap is not None:
        return (f"; this folder holds a COLMAP reconstruction ({colmap.relative_to(data).as_posix() or '.'}/cameras."
                f"{'bin' if (colmap / 'cameras.bin').is_file() else 'txt'}): convert it with ns-process-data images "
                f"(or read it with colmap-data --data {data})")
    folders = sorted(p for p in data.iterdir() if p.is_dir()) if data.is_dir() else []
    subs = [(sub, parser) for sub in folders for parser, marker in _LAYOUT_MARKERS.items() if (sub / marker).is_file()]
    if subs:
        return "; its sub-folders hold scenes: " + ", ".join(f"{parser} --data {sub}" for sub, parser in subs)
    return ""


def _load_json(path: Path, expected: str) -> dict:
    if not path.is_file():
        raise InputError(f"{path}: file not found; expected {expected}{_layout_hint(path.parent)}")
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: not valid JSON ({err}); expected {expected}") from None
    except RecursionError:
        raise InputError(f"{path}: not valid JSON (nested too deeply); expected {expected}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames", []), list):
        raise InputError(f"{path}: holds a {type(meta).__name__ if not isinstance(meta, dict) else 'frames value that is not a list'}; "
                         f"expected {expected}")
    return meta


def _shown(value) -> str:
    """``repr(value)``, cut to a length that fits in an error line."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _numbers(value, *shape: int) -> bool:
    """``value`` is a finite number (no shape) or nested lists of them with this shape."""
    if not shape:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    return isinstance(value, list) and len(value) == shape[0] and all(_numbers(v, *shape[1:]) for v in value)


def _frame_image(data: Path, frame, i: int, key: str, source: Path, suffix: str = "") -> Path:
    """The image frame ``i`` of ``source`` names under ``key``: a relative path inside the scene folder
    ``data`` (checked on the path's text, so symlinks inside the folder still work)."""
    if not isinstance(frame, dict) or not isinstance(frame.get(key), str) or not frame[key].strip() or "\0" in frame[key]:
        raise InputError(f"{source}: frame {i} has no {key!r} (a file name of an image in the scene folder)")
    relative = (frame[key].replace("./", "") if suffix else frame[key]) + suffix  # as the host's parser reads it
    image = Path(os.path.normpath(data / relative))
    if os.path.isabs(relative) or not image.is_relative_to(os.path.normpath(data)):
        raise InputError(f"{source}: frame {i}'s {key} {_shown(frame[key])} points outside the scene folder {data}; keep a "
                         "scene's images inside its folder and name them by relative paths")
    return image


_READABLE: Dict[Path, Tuple[int, int]] = {}
"""Images already found readable in this process, with their (size, mtime_ns): ns-train checks the
data before it writes the run folder and again when the data manager is built."""


def check_image_readable(path: Path, what: str) -> None:
    """``path`` is an image PIL can identify and whose data is complete (``verify``: the PNG chunks'
    CRCs, JPEG markers); a damaged one is named here instead of failing while images are cached."""
    from PIL import Image

    try:
        stat = path.stat()
        key = (stat.st_size, stat.st_mtime_ns)
        if _READABLE.get(path) == key:
            return
        with Image.open(path) as im:
            im.verify()
    except Exception as err:  # noqa: BLE001  (PIL raises many kinds: UnidentifiedImageError, SyntaxError, OSError...)
        raise InputError(f"{path}: cannot be read as an image ({type(err).__name__}: {str(err).strip() or 'damaged data'}; "
                         f"{what}); the file is truncated or damaged: replace it or drop its frame") from None
    _READABLE[path] = key


def _check_sdfstudio(data: Path) -> None:
    expected = "an SDFStudio scene: meta_data.json with height, width, scene_box.aabb and frames"
    meta = _load_json(data / "meta_data.json", expected)
    for key in ("height", "width", "frames", "scene_box"):
        if key not in meta:
            raise InputError(f"{data / 'meta_data.json'}: missing key {key!r}; expected {expected}")
    source = data / "meta_data.json"
    if not isinstance(meta["scene_box"], dict) or not _numbers(meta["scene_box"].get("aabb"), 2, 3):
        raise InputError(f"{source}: scene_box has no 'aabb' ([[xmin, ymin, zmin], [xmax, ymax, zmax]])")
    for key in ("height", "width"):
        if not (isinstance(meta[key], int) and not isinstance(meta[key], bool) and meta[key] > 0):
            raise InputError(f"{source}: {key} is {_shown(meta[key])}; expected the images' {key} in pixels")
    if not meta["frames"]:
        raise InputError(f"{source}: 'frames' is empty; expected at least one image")
    for i, frame in enumerate(meta["frames"]):
        image = _frame_image(data, frame, i, "rgb_path", source)
        for key in ("intrinsics", "camtoworld"):
            if key not in frame:
                raise InputError(f"{source}: frame {i} has no {key!r}")
            if not _numbers(frame[key], 4, 4):
                raise InputError(f"{source}: frame {i}'s {key} is not a 4x4 matrix of numbers")
        if not image.is_file():
            raise InputError(f"{image}: image not found (frame {i} of meta_data.json)")
        check_image_readable(image, f"frame {i} of meta_data.json")


def _check_blender(data: Path, splits: Sequence[str]) -> None:
    for split in splits:
        name = f"transforms_{split}.json"
        expected = f"a Blender scene: {name} with camera_angle_x and frames"
        meta = _load_json(data / name, expected)
        for key in ("camera_angle_x", "frames"):
            if key not in meta:
                raise InputError(f"{data / name}: missing key {key!r}; expected {expected}")
        if not _numbers(meta["camera_angle_x"]) or not 0 < meta["camera_angle_x"] < math.pi:
            raise InputError(f"{data / name}: camera_angle_x is {_shown(meta['camera_angle_x'])}; expected the horizontal field "
                             "of view in radians, between 0 and pi")
        if not meta["frames"]:
            raise InputError(f"{data / name}: 'frames' is empty; expected at least one image")
        for i, frame in enumerate(meta["frames"]):
            image = _frame_image(data, frame, i, "file_path", data / name, ".png")
            if not _numbers(frame.get("transform_matrix"), 4, 4):
                raise InputError(f"{data / name}: frame {i}'s transform_matrix is not a 4x4 matrix of numbers")
            if not image.is_file():
                raise InputError(f"{image}: image not found (frame {i} of {name}; file_path + '.png')")
            check_image_readable(image, f"frame {i} of {name}")


def _check_nerfstudio(data: Path) -> None:
    """nerfstudio-data (``ns-train``'s default dataparser): ``transforms.json`` in the folder (or
    ``--data`` naming that file), and every image it names that is there readable (a damaged one
    would stop a data-loader worker, and the run would hang behind its traceback)."""
    source = data if data.suffix == ".json" else data / "transforms.json"
    expected = "a nerfstudio capture: transforms.json with frames (nerfstudio-data, the default dataparser)"
    meta = _load_json(source, expected)
    for i, frame in enumerate(meta.get("frames", [])):
        name = frame.get("file_path") if isinstance(frame, dict) else None
        image = source.parent / name if isinstance(name, str) and name.strip() and "\0" not in name else None
        if image is not None and image.is_file():  # the host may read a missing one from images_N, or name it itself
            check_image_readable(image, f"frame {i} of {source.name}")


LAYOUT_CHECKED = (SDFStudioDataParserConfig, BlenderDataParserConfig, NerfstudioDataParserConfig)
"""Dataparsers whose files :func:`check_data_layout` knows: checked before a run writes anything,
also under a host's data manager (``sp-train`` on a host method)."""


def check_data_layout(dataparser: object, data: Optional[Path], test_split: str = "val") -> None:
    """The folder exists and holds the files the chosen dataparser will read."""
    if data is None:
        raise InputError("no data folder given; pass --data DIR")
    data = Path(data)
    if isinstance(dataparser, SDFStudioDataParserConfig):
        layout = "SDFStudio layout (meta_data.json + images)"
    elif isinstance(dataparser, BlenderDataParserConfig):
        layout = "Blender layout (transforms_train.json + images)"
    elif isinstance(dataparser, NerfstudioDataParserConfig):
        layout = "nerfstudio layout (transforms.json + images)"
    else:
        layout = f"layout read by {type(dataparser).__name__}"
    if isinstance(dataparser, NerfstudioDataParserConfig) and data.suffix == ".json" and data.is_file():
        _check_nerfstudio(data)
        return
    if not data.is_dir():
        raise InputError(f"{data}: data folder not found; pass --data DIR pointing at a scene in the {layout}")
    if isinstance(dataparser, SDFStudioDataParserConfig):
        _check_sdfstudio(data)
    elif isinstance(dataparser, BlenderDataParserConfig):
        _check_blender(data, ["train", test_split])
    elif isinstance(dataparser, NerfstudioDataParserConfig):
        _check_nerfstudio(data)


# -- images and cameras ---------------------------------------------------------------------


def check_image_sizes(outputs: DataparserOutputs, source: str = "its camera") -> None:
    """Every image has the size its camera was given (mixed sizes break batching and rays)."""
    from PIL import Image

    cams = outputs.cameras
    for i, path in enumerate(outputs.image_filenames):
        check_image_readable(Path(path), f"image {i} of the dataparser's split")
        with Image.open(path) as im:
            w, h = im.size
        want_w, want_h = int(cams.width[i]), int(cams.height[i])
        if (w, h) != (want_w, want_h):
            raise InputError(
                f"{path}: image is {w}x{h} pixels, expected {want_w}x{want_h} like {source}; "
                "all images of a scene must have the size their cameras were calibrated for"
            )


def ray_hits_box(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """``[N]`` bool: the ray ``o + t d`` (t >= 0) meets the box ``aabb`` ``[2, 3]`` (slab test)."""
    safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0 = (aabb[0] - origins) / safe
    t1 = (aabb[1] - origins) / safe
    t_near = torch.minimum(t0, t1).amax(-1)
    t_far = torch.maximum(t0, t1).amin(-1)
    return (t_far >= t_near.clamp(min=0.0)) & (t_far >= 0)


def check_cameras_look_into_box(outputs: DataparserOutputs, source: str = "the scene box") -> None:
    """Each camera's optical axis passes through the scene box, i.e. the box holds what the
    cameras look at (a box in the wrong units or frame fails here, not as a blank render)."""
    c2w = outputs.cameras.camera_to_worlds.float().reshape(-1, 3, 4)  # one camera may come unbatched
    origins = c2w[:, :3, 3]
    forward = -c2w[:, :3, 2]  # nerfstudio cameras look along -z
    aabb = outputs.scene_box.aabb.float()
    hits = ray_hits_box(origins, forward, aabb)
    if not bool(hits.all()):
        bad = [i for i in range(len(hits)) if not bool(hits[i])]
        i = bad[0]
        raise InputError(
            f"{outputs.image_filenames[i]}: its camera (at {[round(v, 3) for v in origins[i].tolist()]}) looks past "
            f"{source} {[[round(v, 3) for v in row] for row in aabb.tolist()]}; {len(bad)} of {len(hits)} cameras do. "
            "Expected a box that contains the object all cameras look at: fix the box (or the poses' units/frame)"
        )
