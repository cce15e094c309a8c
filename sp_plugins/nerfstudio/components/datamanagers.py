"""Data managers that check their input and feed surface models from any layout.

- :class:`SurfaceDataset` is nerfstudio's ``SDFDataset`` without the demand for depth and normal
  metadata, so NeuS-family models also train on ``blender-data`` (and on ``sdfstudio-data``
  without monocular priors).
- :class:`CheckedDataManager` (and :class:`SurfaceDataManager`) check the data before training:
  the folder and its layout, image sizes against the cameras, and that every camera looks into
  the scene box. Each failure is an :class:`InputError` (a ``ValueError``) naming the file and
  what was expected; under ``ns-train`` it prints as one line. ``ns-eval`` prints one line per
  evaluated image (nerfstudio's own bar is silent outside a terminal and moves once per image,
  which on a CPU can be minutes).
- :class:`SurfaceDataManager` also takes ``--pipeline.datamanager.object-box R``: the SDF models
  the cube ``[-R, R]^3`` (the object) and the background model the rest. Real captures read
  with ``instant-ngp-data`` come with a box of ``aabb_scale / 2`` (the fox: +-2), which holds
  the room and the cameras too.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple, Type

import torch
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.datasets.sdf_dataset import SDFDataset
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader

from sp_plugins.adapter.checks import check_device
from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio.host import HOST
from sp_plugins.nerfstudio.components.views import ViewSelection, select_views
from sp_plugins.nerfstudio.model import hold_under_host_command


class SurfaceDataset(SDFDataset):
    """``SDFDataset`` that treats depth / normal metadata as optional."""

    def __init__(self, dataparser_outputs: DataparserOutputs, scale_factor: float = 1.0):
        meta = dict(dataparser_outputs.metadata)
        for key in ("depth_filenames", "normal_filenames", "camera_to_worlds", "transform"):
            meta.setdefault(key, None)
        meta.setdefault("include_mono_prior", False)
        if meta["include_mono_prior"] and not meta["depth_filenames"]:
            raise InputError(
                "include_mono_prior=True but the data has no mono_depth_path / mono_normal_path entries; "
                "add them to meta_data.json or drop --include-mono-prior"
            )
        super().__init__(dataclasses.replace(dataparser_outputs, metadata=meta), scale_factor)


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


# -- data managers ------------------------------------------------------------------------------


@dataclass
class CheckedDataManagerConfig(VanillaDataManagerConfig):
    """Vanilla data manager that validates the data first (no worker processes)."""

    _target: Type = field(default_factory=lambda: CheckedDataManager)
    check_data: bool = True
    """Check the data folder, image sizes and scene box before training."""
    train_views: int = -1
    """Train on only this many of the training views (sparse-view setting); -1 uses all."""
    train_view_selection: ViewSelection = "spread"
    """Which views: spread (farthest camera centres from view 0), first, or random (seeded)."""
    train_view_seed: int = 0
    """Seed of the random view selection."""


class CheckedDataManager(VanillaDataManager):
    """``VanillaDataManager`` with clear errors for bad input."""

    config: CheckedDataManagerConfig
    dataset_type = InputDataset  # type: ignore[assignment]  (shadows the generic lookup)

    def __init__(self, config: CheckedDataManagerConfig, device="cpu", test_mode="val", world_size=1, local_rank=0, **kwargs):
        hold_under_host_command(self)  # a host command on a run of ours: its failures as one line
        check_device(torch.device(device).type, flags=HOST.flags)
        self._checks = config.check_data and test_mode != "inference"
        if self._checks:
            data = config.data if config.data is not None else config.dataparser.data
            check_data_layout(config.dataparser, data, "test" if test_mode == "test" else "val")
        super().__init__(config, device=device, test_mode=test_mode, world_size=world_size, local_rank=local_rank, **kwargs)

    def _size_source(self, outputs: DataparserOutputs) -> str:
        if isinstance(self.config.dataparser, SDFStudioDataParserConfig):
            return "meta_data.json's height and width"
        if isinstance(self.config.dataparser, BlenderDataParserConfig):
            return f"the first image {outputs.image_filenames[0]}"
        return "its camera"

    def _box_source(self) -> str:
        parser = self.config.dataparser
        if isinstance(parser, SDFStudioDataParserConfig):
            data = self.config.data if self.config.data is not None else parser.data
            return f"the scene box (scene_box.aabb of {Path(data) / 'meta_data.json'})"
        if isinstance(parser, BlenderDataParserConfig):
            return "the Blender scene box (fixed; poses are scaled by --scale-factor)"
        return "the scene box"

    def _checked(self, dataset: InputDataset) -> InputDataset:
        if self._checks:
            outputs = dataset._dataparser_outputs
            check_image_sizes(outputs, self._size_source(outputs))
            check_cameras_look_into_box(outputs, self._box_source())
        return dataset

    def _adjusted(self, outputs: DataparserOutputs) -> DataparserOutputs:
        """Hook for subclasses: change the dataparser's outputs (both splits) before use."""
        return outputs

    def create_train_dataset(self):
        c = self.config
        outputs = select_views(self.train_dataparser_outputs, c.train_views, c.train_view_selection, c.train_view_seed)
        self.train_dataparser_outputs = self._adjusted(outputs)
        return self._checked(super().create_train_dataset())

    def create_eval_dataset(self):
        outputs = self._adjusted(self.dataparser.get_dataparser_outputs(split=self.test_split))
        dataset = self.dataset_type(dataparser_outputs=outputs, scale_factor=self.config.camera_res_scale_factor)
        if self.test_mode == "test" and len(dataset) == 0:
            raise InputError(
                f"{self.config.data or getattr(self.config.dataparser, 'data', '')}: the dataparser's {self.test_split} split "
                "holds no images, so there is nothing to evaluate; train with a split that keeps some "
                "(e.g. instant-ngp-data --train-split-fraction 0.8)"
            )
        return self._checked(dataset)

    def setup_eval(self):
        super().setup_eval()
        self.fixed_indices_eval_dataloader = ProgressEvalDataloader(
            input_dataset=self.eval_dataset, device=self.device, num_workers=self.world_size * 4
        )


class ProgressEvalDataloader(FixedIndicesEvalDataloader):
    """nerfstudio's all-images evaluation loader that prints one line per image to stderr."""

    def __next__(self):
        now = time.perf_counter()
        if self.count > 0:
            print(f"  image {self.count}/{len(self.image_indices)} took {now - self._started:.1f} s", file=sys.stderr, flush=True)
        if self.count < len(self.image_indices):
            i = self.image_indices[self.count]
            cams = self.input_dataset.cameras
            print(f"evaluating image {self.count + 1}/{len(self.image_indices)} ({int(cams.width[i])}x{int(cams.height[i])})",
                  file=sys.stderr, flush=True)
        self._started = now
        return super().__next__()


@dataclass
class SurfaceDataManagerConfig(CheckedDataManagerConfig):
    """Checked data manager whose dataset serves SDF models."""

    _target: Type = field(default_factory=lambda: SurfaceDataManager)
    object_box: Optional[float] = None
    """Half side R of the cube [-R, R]^3 (in the dataparser's scaled frame) where the SDF models the
    object; rays leave it for the background model. None keeps the dataparser's box (for a real
    capture read with instant-ngp-data that box, aabb_scale / 2, also holds the room)."""


class SurfaceDataManager(CheckedDataManager):
    config: SurfaceDataManagerConfig
    dataset_type = SurfaceDataset  # type: ignore[assignment]

    def _adjusted(self, outputs: DataparserOutputs) -> DataparserOutputs:
        r = self.config.object_box
        if r is None:
            return outputs
        if not r > 0:
            raise InputError(f"--pipeline.datamanager.object-box {r}: must be a positive half side (scene units)")
        box = SceneBox(aabb=torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32))
        return dataclasses.replace(outputs, scene_box=box)

    def _box_source(self) -> str:
        if self.config.object_box is not None:
            return f"the object box (--pipeline.datamanager.object-box {self.config.object_box})"
        return super()._box_source()
