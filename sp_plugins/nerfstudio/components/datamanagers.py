"""Data managers that check their input and feed surface models from any layout.

- :class:`SurfaceDataset` is nerfstudio's ``SDFDataset`` without the demand for depth and normal
  metadata, so NeuS-family models also train on ``blender-data`` (and on ``sdfstudio-data``
  without monocular priors).
- :class:`CheckedDataManager` (and :class:`SurfaceDataManager`) check the data before training
  (:mod:`~sp_plugins.nerfstudio.components.data_checks`): the folder and its layout, image sizes against the
  cameras, and that every camera looks into the scene box. Each failure is an :class:`InputError` (a ``ValueError``) naming the file and
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
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Type

import torch
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.datasets.sdf_dataset import SDFDataset
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader

from sp_plugins.adapter.checks import check_device
from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio.host import HOST
from sp_plugins.nerfstudio.components.data_checks import check_cameras_look_into_box, check_data_layout, check_image_sizes
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
