"""Seeded ray workers for nerfstudio's ``ParallelDataManager`` (registry entry ``nerfstudio_parallel_seed``).

nerfstudio 1.1.5's ``ParallelDataManager`` (nerfacto's and most of its own methods' data manager)
draws the training rays in ``DataProcessor`` processes it starts with ``spawn``. A spawned process
does not inherit the trainer's seed (``_set_random_seed`` runs in the trainer's process only), and
torch seeds its default generator from the operating system at start-up: every batch's pixels,
and with them the whole run, differed between two runs of the same command (25 of nerfacto's 28
weight tensors after 3 steps).

Within the scope, ``parallel_datamanager.DataProcessor`` builds
:class:`~sp_plugins.nerfstudio.components.parallel_data.SeededDataProcessor`: the host's worker,
which first seeds torch, numpy and Python's ``random`` from the trainer process's seed (its
``torch.initial_seed()``) plus one plus the worker's index. Scope: the ``setup_train`` of
:class:`~sp_plugins.nerfstudio.components.parallel_data.RepeatableParallelDataManager` (what
``with_sp`` gives a method whose data manager is nerfstudio's), and ``sp-train``'s whole process
(a plugin's own subclass of the data manager). With ``num_processes`` above 1 the workers' batches
still interleave in the order they finish: one worker (the default) repeats.
"""

from __future__ import annotations

import contextlib
import inspect
import itertools
from typing import Iterator

from sp_plugins.patches.registry import Patch, nerfstudio_patch, swapped

__all__ = ["PATCH", "seeded_workers"]

MODULE = "nerfstudio.data.datamanagers.parallel_datamanager"
NAME = "DataProcessor"
TESTED_NERFSTUDIO_VERSIONS = ("1.1.5",)


@contextlib.contextmanager
def seeded_workers() -> Iterator[None]:
    """Within this block, the workers a ``ParallelDataManager`` starts seed themselves."""
    import torch
    from nerfstudio.data.datamanagers import parallel_datamanager

    from sp_plugins.nerfstudio.components.parallel_data import SeededDataProcessor  # defers nerfstudio

    index = itertools.count()

    def build(*args, **kwargs):
        return SeededDataProcessor(*args, seed=torch.initial_seed() + 1 + next(index), **kwargs)

    with swapped(parallel_datamanager, NAME, build):
        yield


def _check(patch: Patch) -> None:
    from nerfstudio.data.datamanagers import parallel_datamanager

    real = getattr(parallel_datamanager, NAME, None)
    patch.expect(inspect.isclass(real), f"{MODULE}.{NAME} a class", f"{MODULE}.{NAME} = {type(real).__name__}")
    patch.expect(callable(getattr(real, "run", None)), f"{NAME}.run", "no run method")
    manager = getattr(parallel_datamanager, "ParallelDataManager", None)
    patch.expect(inspect.isclass(manager), f"{MODULE}.ParallelDataManager a class", f"{type(manager).__name__}")
    source = inspect.getsource(manager.setup_train)
    patch.expect(f"{NAME}(" in source, f"ParallelDataManager.setup_train building {NAME}(...) by its module name",
                 "a setup_train that does not")


PATCH = nerfstudio_patch(
    "nerfstudio_parallel_seed", TESTED_NERFSTUDIO_VERSIONS, _check, seeded_workers,
    ((MODULE, NAME), (MODULE, "ParallelDataManager")), owned_commands=("sp-train",),
    changes=f"{MODULE}.{NAME}: a worker that seeds torch, numpy and random from the trainer's seed before it draws rays",
    scope_text="RepeatableParallelDataManager.setup_train (with_sp's data manager) and sp-train's process")
