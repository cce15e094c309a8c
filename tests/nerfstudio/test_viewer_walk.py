"""Nothing of ours raises when read: the objects nerfstudio's viewer walks, for every method
we register and for ``sp-train`` on nerfstudio's built-ins, before the trainer sets the step count and
after a training step.

nerfstudio 1.1.5's default front end is the web viewer; ``Viewer.__init__`` walks the pipeline with
``nerfstudio/viewer/utils.py: parse_object``, which ``getattr``\\ s every attribute of every module
(skipping only ``cached_property``). It does so in ``Trainer.setup``, after the pipeline and the
optimizers are built and before the training callbacks give our models the run's length. A property
that raises there stops ``ns-train`` before its first step: the preconditioner's ``schedule`` did
("end=0.2 is a fraction of training"), for every SP method, and the suite, which ran with
``--vis tensorboard``, never saw it.

Here the viewer's own ``parse_object`` walks each pipeline as ``Viewer.__init__`` calls it, and a
stricter walk reads every attribute (cached properties included) of every object of ours reachable
from the pipeline or the config; configs also go through ``dataclasses.replace``, ``copy.deepcopy``
and ``repr``, as tyro, nerfstudio and debuggers use them.
"""

from __future__ import annotations

import copy
import dataclasses
import types
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("nerfstudio")

from tests.helpers.ns_configs import (
    SDF_METHODS, in_process_data, run_recording, shrink_model, sp_train_config, tiny_radiance_config, tiny_sdf_config,
)
from sp_plugins.nerfstudio.runs import configure_run, our_methods

OURS = tuple(sorted(our_methods()))
"""Every entry point of ours in the ``nerfstudio.method_configs`` group."""

BUILTINS = ("nerfacto", "mipnerf", "neus", "tensorf", "vanilla-nerf")
"""nerfstudio's built-ins under ``sp-train`` (``with_sp``), one of each field family it reaches."""

STEPS = 10
"""The run's length: SP ends at half of it (a fractional end, unknown until the trainer says)."""

END = 0.5


def tiny(name: str, scene: Path, out: Path):
    """A CPU-sized trainer config of ``name`` (ours, or ``sp-train BUILTIN``) whose SP ends at a
    fraction of training."""
    if name.startswith("sp-train "):
        config = sp_train_config(name.split()[1])
        shrink_model(config.pipeline.model)
        in_process_data(config)
        config.pipeline.model.sp.end = END
        layout = "sdfstudio" if hasattr(config.pipeline.model, "sdf_field") else "blender"
        return configure_run(config, scene / layout, steps=STEPS, output_dir=out, rays_per_batch=32)
    if name in SDF_METHODS:
        return tiny_sdf_config(name, scene, out, steps=STEPS, end=END)
    return tiny_radiance_config(name, scene, out, steps=STEPS, rays=32, end=END)


# -- the walks ----------------------------------------------------------------------------------------
def viewer_walk(pipeline) -> None:
    """``Viewer.__init__``'s reads of the pipeline (nerfstudio 1.1.5, viewer/viewer.py): its own
    ``parse_object`` for each element type it collects."""
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer_elements import ViewerControl, ViewerElement
    from nerfstudio.viewer_legacy.server.viewer_elements import ViewerElement as LegacyViewerElement

    for kind in (LegacyViewerElement, ViewerElement, ViewerControl):
        parse_object(pipeline, kind, "Custom Elements")


def ours(obj) -> bool:
    """An object whose class, or a class it derives from, is defined in sp_plugins (our mixins on host
    classes and the generated SP variants included)."""
    return any((getattr(cls, "__module__", "") or "").startswith("sp_plugins") for cls in type(obj).__mro__)


LEAVES = (str, bytes, int, float, complex, bool, type(None), torch.Tensor, np.ndarray, np.generic, type, types.ModuleType,
          types.FunctionType, types.BuiltinFunctionType, types.MethodType, types.MethodWrapperType, Path, torch.dtype,
          torch.device, torch.Generator)


def children(obj):
    """What a walker reaches from ``obj``: container items, attributes, an ``nn.Module``'s children."""
    if isinstance(obj, dict):
        return list(obj.values())
    if isinstance(obj, (list, tuple, set, frozenset)):
        return list(obj)
    found = list(vars(obj).values()) if hasattr(obj, "__dict__") else []
    if isinstance(obj, torch.nn.Module):
        found += list(obj._modules.values())
    return found


def read_everything(root, where: str, limit: int = 50_000) -> list:
    """``getattr`` of every name in ``dir()`` of every object of ours reachable from ``root`` (nothing
    skipped, cached properties included); the reads that raised, as ``path.name: error``. Host objects
    are walked through, not read: what they raise is the host's."""
    failures, seen, queue = [], set(), [(root, where)]
    while queue and len(seen) < limit:
        obj, path = queue.pop()
        if isinstance(obj, LEAVES) or id(obj) in seen:
            continue
        seen.add(id(obj))
        if ours(obj):
            for name in dir(obj):
                try:
                    value = getattr(obj, name)
                except Exception as err:  # noqa: BLE001 - what is collected is what a walker would die of
                    failures.append(f"{path}.{name}: {type(err).__name__}: {err}")
                    continue
                if not name.startswith("__"):
                    queue.append((value, f"{path}.{name}"))
        for i, child in enumerate(children(obj)):
            queue.append((child, f"{path}[{i}]"))
    return failures


def config_walk(config) -> list:
    """tyro's and nerfstudio's reads of a config: ``repr``, ``copy.deepcopy``, ``dataclasses.replace`` of
    every dataclass in it, and every attribute of our config objects; the failures."""
    failures = read_everything(config, "config")
    repr(config)
    copy.deepcopy(config)
    seen, queue = set(), [(config, "config")]
    while queue:
        obj, path = queue.pop()
        if id(obj) in seen or isinstance(obj, LEAVES):
            continue
        seen.add(id(obj))
        if dataclasses.is_dataclass(obj):
            try:
                dataclasses.replace(obj)
            except Exception as err:  # noqa: BLE001
                if ours(obj):
                    failures.append(f"dataclasses.replace({path}): {type(err).__name__}: {err}")
            queue += [(getattr(obj, f.name, None), f"{path}.{f.name}") for f in dataclasses.fields(obj)]
        elif isinstance(obj, (dict, list, tuple)):
            queue += [(v, f"{path}[{i}]") for i, v in enumerate(obj.values() if isinstance(obj, dict) else obj)]
    return failures


# -- the test -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", [*OURS, *(f"sp-train {m}" for m in BUILTINS)])
def test_the_viewer_walks_every_method_before_and_after_the_step_count_is_set(name, tiny_scene, tmp_path):
    config = tiny(name, tiny_scene, tmp_path)
    assert not config_walk(config)

    # what Trainer.setup has built when it starts the viewer: the pipeline and its optimizers, no callbacks
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.pipeline = config.pipeline.setup(device="cpu", test_mode="val", world_size=1, local_rank=0,
                                             grad_scaler=trainer.grad_scaler)
    trainer.optimizers = trainer.setup_optimizers()
    viewer_walk(trainer.pipeline)
    assert not read_everything(trainer.pipeline, "pipeline")
    sp = getattr(trainer.pipeline.model, "sp", None)
    if sp is not None:
        assert sp.schedule is None, "the step count is known already: this walk did not see the unknown state"
    del trainer

    # after setup and one training step
    trainer, record = run_recording(config, stop_after=0)
    assert len(record) == 1
    sp = getattr(trainer.pipeline.model, "sp", None)
    if sp is not None:
        assert sp.schedule is not None and sp.total_steps == STEPS
    viewer_walk(trainer.pipeline)
    assert not read_everything(trainer.pipeline, "pipeline")
    assert not config_walk(config)
