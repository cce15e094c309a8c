"""nerfstudio's parallel data manager with ray workers that repeat run to run.

The workers of nerfstudio's ``ParallelDataManager`` are spawned processes that do not see the
trainer's seed (``patches/nerfstudio_parallel_seed.py`` says why and what changes).
:func:`repeatable_datamanager` points a method's data-manager config at
:class:`RepeatableParallelDataManager` when it is nerfstudio's own, which is what ``with_sp``
does for every SP variant; a saved ``config.yml`` that names nerfstudio's class still loads.
"""

from __future__ import annotations

import random

import numpy as np
import torch
from nerfstudio.data.datamanagers.parallel_datamanager import DataProcessor, ParallelDataManager

from sp_plugins.patches import registry

__all__ = ["RepeatableParallelDataManager", "SeededDataProcessor", "repeatable_datamanager"]


class SeededDataProcessor(DataProcessor):
    """nerfstudio's ray worker, seeded in its own process before it draws a ray."""

    def __init__(self, *args, seed: int, **kwargs):
        super().__init__(*args, **kwargs)
        self.seed = int(seed)

    def run(self):
        torch.manual_seed(self.seed)
        np.random.seed(self.seed % 2**32)
        random.seed(self.seed)
        super().run()


class RepeatableParallelDataManager(ParallelDataManager):
    """``ParallelDataManager`` whose workers seed themselves from the trainer's seed."""

    def setup_train(self):
        with registry.scope("nerfstudio_parallel_seed"):
            super().setup_train()


def repeatable_datamanager(datamanager_config) -> None:
    """Point ``datamanager_config`` (in place) at :class:`RepeatableParallelDataManager` when it
    targets nerfstudio's ``ParallelDataManager`` itself; any other data manager is left as it is."""
    if getattr(datamanager_config, "_target", None) is ParallelDataManager:
        datamanager_config._target = RepeatableParallelDataManager
