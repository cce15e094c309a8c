"""CUDA-only calls in sdfstudio's timer, train loop and mesh extraction, made CPU-safe.

Targets sdfstudio commit 370902a, which assumes a GPU in four places:

- ``nerfstudio/utils/writer.py``: ``TimeWriter.__enter__`` / ``__exit__`` call
  ``torch.cuda.synchronize()`` (wraps every training step);
- ``scripts/train.py``: ``train_loop`` calls ``torch.cuda.set_device(local_rank)`` even for
  ``--machine.num-gpus 0``;
- ``nerfstudio/utils/marching_cubes.py``: ``get_surface_sliding`` (ns-extract-mesh's SDF path)
  and ``get_surface_sliding_with_contraction`` move their grids with ``.cuda()``;
- ``nerfstudio/data/dataparsers/{sdfstudio,monosdf}_dataparser.py``: with ``--load-pairs True``
  (GeoNeuS patch warping: geo-neus, geo-volsdf, geo-unisurf and their SP variants) the parser
  moves every training image to the GPU with ``.cuda()``. ns-train runs it inside ``train_loop``
  (already CPU-safe); ns-eval and ``eval_setup`` do not.

Each is wrapped so that, only while no CUDA device is available, the call runs with that CUDA
function replaced by its CPU meaning (synchronize: nothing to wait for; set_device: stay on the
CPU; ``Tensor.cuda()``: stay where the tensor is, the model's device on a CPU run). With a GPU the
original code runs unchanged.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Callable, Iterator

import torch

from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT, after_exec

__all__ = ["HOST_COMMIT", "cpu_meaning", "install"]

_MARK = "_sp_cpu_safe"


@contextlib.contextmanager
def cpu_meaning() -> Iterator[None]:
    """While no CUDA device is available: ``torch.cuda.synchronize`` / ``set_device`` do nothing
    and ``Tensor.cuda()`` returns the tensor itself. With CUDA, nothing changes."""
    if torch.cuda.is_available():
        yield
        return
    saved = torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda
    torch.cuda.synchronize = lambda *args, **kwargs: None
    torch.cuda.set_device = lambda *args, **kwargs: None
    torch.Tensor.cuda = lambda self, *args, **kwargs: self
    try:
        yield
    finally:
        torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda = saved


def cpu_safe(fn: Callable) -> Callable:
    """``fn`` run inside :func:`cpu_meaning`."""
    if getattr(fn, _MARK, False):
        return fn

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with cpu_meaning():
            return fn(*args, **kwargs)

    setattr(wrapper, _MARK, True)
    return wrapper


def _patch_writer(module) -> None:
    cls = module.TimeWriter
    cls.__enter__ = cpu_safe(cls.__enter__)
    cls.__exit__ = cpu_safe(cls.__exit__)


def _patch_train(module) -> None:
    module.train_loop = cpu_safe(module.train_loop)


MESH_FUNCTIONS = ("get_surface_sliding", "get_surface_sliding_with_contraction")


def _patch_marching_cubes(module) -> None:
    for name in MESH_FUNCTIONS:
        setattr(module, name, cpu_safe(getattr(module, name)))


def _patch_extract_mesh(module) -> None:  # it imported the functions by name
    for name in MESH_FUNCTIONS:
        if hasattr(module, name):
            setattr(module, name, cpu_safe(getattr(module, name)))


PAIR_PARSERS = {
    "nerfstudio.data.dataparsers.sdfstudio_dataparser": "SDFStudio",
    "nerfstudio.data.dataparsers.monosdf_dataparser": "MonoSDFScene",
}


def _patch_parser(module) -> None:
    cls = getattr(module, PAIR_PARSERS[module.__name__])
    cls._generate_dataparser_outputs = cpu_safe(cls._generate_dataparser_outputs)


def install() -> None:
    after_exec("nerfstudio.utils.writer", _patch_writer)
    after_exec("scripts.train", _patch_train)
    after_exec("nerfstudio.utils.marching_cubes", _patch_marching_cubes)
    after_exec("scripts.extract_mesh", _patch_extract_mesh)
    for name in PAIR_PARSERS:
        after_exec(name, _patch_parser)
