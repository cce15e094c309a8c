"""The one nerfbaselines method class behind every spec of ours: nerfbaselines' own nerfstudio
wrapper (``nerfbaselines.methods.nerfstudio.NerfStudio``, its ``python`` backend), subclassed where
it falls short for our methods:

- the nerfstudio method comes from the spec id (:data:`sp_plugins.nerfbaselines.specs.ENTRIES`);
  ``<id>+sp`` puts SP on it with ``with_sp``;
- the built model's SP state is checked against what the id promises, and recorded in ``hparams``
  (:mod:`~sp_plugins.nerfbaselines.sp_state`); a ``--set pipeline.model.sp.enabled`` against an
  ``+sp`` / ``+sp-off`` id is refused in one line, naming the id that trains so;
- ``--set`` values are typed to their field and an unknown key is refused in one line
  (:mod:`~sp_plugins.nerfbaselines.overrides`), exit status 2, before the trainer is built;
- models that name their image ``rgb_fine`` (vanilla-nerf, MipNeRF) render it as ``rgb``;
- the dataset's scene box (:mod:`~sp_plugins.nerfbaselines.scene_box`);
- seeded from ``machine.seed`` as ``ns-train`` is (nerfbaselines does not seed);
- LPIPS offline: our models and nerfstudio's build under the registry's ``nerfstudio_lpips`` scope,
  and nerfbaselines' own LPIPS runs under ``nerfbaselines_lpips`` while this method exists.
"""

from __future__ import annotations

import copy
import functools
import logging
import os
import sys
from typing import Any, Optional

from nerfbaselines.methods.nerfstudio import NerfStudio

from sp_plugins.nerfbaselines import scene_box, sp_state, specs
from sp_plugins.nerfbaselines.outputs import with_output_aliases
from sp_plugins.nerfbaselines.overrides import OverrideError, apply_overrides
from sp_plugins.nerfstudio import with_sp
from sp_plugins.patches import registry

__all__ = ["SPNerfStudio", "seed"]

log = logging.getLogger("sp_plugins.nerfbaselines")
PASSED = ("method", "pipeline.datamanager.dataparser")
"""Override keys nerfbaselines' wrapper itself interprets (the rest are ours to type and set)."""
SP_ENABLED = "pipeline.model.sp.enabled"


def refuse(message: str) -> None:
    """One line on stderr, exit status 2 (nothing of the trainer is built yet)."""
    print(f"nerfbaselines: error: {message}", file=sys.stderr, flush=True)
    raise SystemExit(2)


def seed(value: int) -> None:
    """Seed Python, NumPy and torch as ``ns-train`` does before it builds the trainer (nerfbaselines'
    wrapper does not), so a run here draws the same weights and rays as ``ns-train`` with that seed."""
    import random

    import numpy as np
    import torch

    random.seed(value)
    np.random.seed(value)
    torch.manual_seed(value)


class SPNerfStudio(NerfStudio):
    """nerfbaselines' nerfstudio wrapper for the nerfstudio method a spec of ours names."""

    def __init__(self, *, checkpoint: Optional[str] = None, train_dataset: Optional[dict] = None,
                 config_overrides: Optional[dict] = None):
        self._sp_id = self.get_method_info().get("method_id", "")
        if self._sp_id not in specs.ENTRIES:
            raise RuntimeError(f"{type(self).__name__} is built by nerfbaselines from one of our specs, not {self._sp_id!r}")
        self._sp_entry = specs.ENTRIES[self._sp_id]
        registry.hold("nerfbaselines_lpips", self)
        if os.environ.get("SP_DETERMINISTIC", "").strip() == "1":  # repeatable at any thread count (patches/torch_deterministic.py)
            registry.hold("torch_deterministic", self)
        overrides = dict(config_overrides or {})
        passed = {key: overrides.pop(key) for key in PASSED if key in overrides}
        # (read by nerfbaselines' __init__; a "method" key it would also try to set as a config field)
        self._default_nerfstudio_name = passed.pop("method", self._sp_entry.nerfstudio_name)
        self._sp_overrides = overrides
        self._sp_state: dict = {}
        self._sp_box = None  # radiance methods keep the box nerfstudio's parser gives (as under ns-train)
        if self._sp_entry.sdf:
            try:
                self._sp_box = scene_box.load(checkpoint) if checkpoint else scene_box.dataset_box(train_dataset)
            except ValueError as err:
                refuse(str(err))
        super().__init__(checkpoint=checkpoint, train_dataset=train_dataset, config_overrides=passed)

    def _sp_config(self, config: Any) -> Any:
        if self._sp_entry.add_sp:
            config = with_sp(config).config
            config.pipeline.model.sp.enabled = not self._sp_entry.sp_off
        try:
            apply_overrides(config, self._sp_overrides, self._sp_id)
        except OverrideError as err:
            refuse(str(err))
        self._refuse_contradicting_set(config)
        if hasattr(config.pipeline.datamanager, "check_data"):  # nerfbaselines' loader read the folder, not ns-train's
            config.pipeline.datamanager.check_data = False
        parser = config.pipeline.datamanager.dataparser
        if self._sp_box is not None and self._sp_entry.sdf and type(parser).__name__ != "BlenderDataParserConfig":
            from nerfstudio.configs.dataparser_configs import all_dataparsers

            log.info("%s: nerfstudio's blender-data parser (poses as given), for the dataset's scene box", self._sp_id)
            config.pipeline.datamanager.dataparser = copy.deepcopy(all_dataparsers["blender-data"])
        return config

    def _setup(self, train_dataset, config_overrides):
        if self.checkpoint is None:
            self.config = self._sp_config(self._original_config)
            self._original_config = copy.deepcopy(self.config)
        seed(self.config.machine.seed)
        with registry.scope("nerfstudio_lpips"):
            super()._setup(train_dataset, config_overrides)
        self._sp_state = sp_state.model_state(self._trainer.pipeline.model)
        sp_state.check(self._sp_id, sp_state.promised(self._sp_id, self.config), self._sp_state)
        if self.checkpoint is not None and self._loaded_step:
            self._restore_step_state(self._loaded_step - 1)

    def _refuse_contradicting_set(self, config: Any) -> None:
        """``--set pipeline.model.sp.enabled`` against an ``+sp`` / ``+sp-off`` id: the row would be
        mislabelled; the other id trains so. (A plain id's SP follows its config: the run records it.)"""
        if SP_ENABLED not in self._sp_overrides or not self._sp_entry.add_sp:
            return
        promise = sp_state.promised(self._sp_id, config)
        if sp_state.config_enabled(config) != promise:
            refuse(f"--set {SP_ENABLED}={self._sp_overrides[SP_ENABLED]}: {self._sp_id} trains with SP "
                   f"{'on' if promise else 'off'}; train {sp_state.twin(self._sp_id)} for SP {'off' if promise else 'on'}")

    def get_info(self):
        """nerfbaselines' info, with what the built model does about SP in ``hparams`` (saved with the results)."""
        info = super().get_info()
        if self._sp_state:
            info["hparams"] = {**info.get("hparams", {}), **sp_state.as_hparams(self._sp_state)}
        return info

    def _restore_step_state(self, step: int) -> None:
        """State that depends on the step and lives outside the state dict (nerfacto's proposal
        anneal, SP's alpha, coarse-to-fine level masks) is set by the model's before-iteration
        callbacks: after loading a checkpoint they run for the last step it trained, so a reloaded
        model renders as the one that was saved (nerfbaselines' wrapper runs none on load)."""
        from nerfstudio.engine.callbacks import TrainingCallbackLocation

        for callback in self._trainer.callbacks:
            callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)

    def _patch_model(self, model_cls, *, config):
        return with_output_aliases(super()._patch_model(model_cls, config=config))

    def _patch_dataparser(self, dataparser_cls, **kwargs):
        made = super()._patch_dataparser(dataparser_cls, **kwargs)
        config = kwargs.get("config")
        identity = config is not None and type(config.pipeline.datamanager.dataparser).__name__ == "BlenderDataParserConfig"
        if self._sp_box is None or not identity:
            return made
        log.info("%s: scene box %s from the dataset (not nerfbaselines' fixed one)", self._sp_id, self._sp_box)
        return functools.partial(scene_box.scene_box_class(made.func, self._sp_box), *made.args, **made.keywords)

    def save(self, path: str):
        super().save(path)
        scene_box.save(path, self._sp_box)
