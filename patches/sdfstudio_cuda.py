"""CUDA-only calls in sdfstudio's timer, train loop and mesh extraction, made CPU-safe (registry
entry ``sdfstudio_cuda``).

Targets sdfstudio commit 370902a, which assumes a GPU in four places:

- ``nerfstudio/utils/writer.py``: ``TimeWriter.__enter__`` / ``__exit__`` call
  ``torch.cuda.synchronize()`` (wraps every training step);
- ``scripts/train.py``: ``train_loop`` calls ``torch.cuda.set_device(local_rank)`` even for
  ``--machine.num-gpus 0``;
- ``nerfstudio/utils/marching_cubes.py``: ``get_surface_sliding`` (ns-extract-mesh's SDF path)
  and ``get_surface_sliding_with_contraction`` move their grids with ``.cuda()``;
- ``nerfstudio/data/dataparsers/{sdfstudio,monosdf}_dataparser.py``: with ``--load-pairs True``
  (GeoNeuS patch warping: geo-neus, geo-volsdf, geo-unisurf and their SP variants) the parser
  moves every training image to the GPU with ``.cuda()``.

Restricted to those modules' own calls:

- the writer's and ``scripts.train``'s module global ``torch`` becomes a view of torch
  (:data:`CPU_TORCH`) whose ``cuda.synchronize`` / ``cuda.set_device`` do nothing while no CUDA
  device is available; ``torch`` itself is not touched, so the training run's other code calls
  the real functions;
- the mesh functions and the two parsers run inside :func:`cpu_meaning`, which (no CUDA only)
  gives ``Tensor.cuda()`` its CPU meaning (stay where the tensor is) for calls made by sdfstudio's
  own code and passes every other caller to torch's; after each call ``torch.Tensor.cuda``,
  ``torch.cuda.synchronize`` and ``torch.cuda.set_device`` are torch's again.

With a GPU the original code runs unchanged.
"""

from __future__ import annotations

import contextlib
import functools
import sys
import types
from typing import Callable, Iterator

import torch

from sp_plugins.patches.registry import Patch
from sp_plugins.patches.sdfstudio_import_hook import (
    HOST_COMMIT, HOST_PACKAGES, expect_attribute, expect_source, patching, sdfstudio_patch,
)

__all__ = ["CPU_TORCH", "HOST_COMMIT", "PATCH", "cpu_meaning", "cpu_safe"]

_MARK = "_sp_cpu_safe"


def _from_host(depth: int = 2) -> bool:
    """Whether the caller ``depth`` frames up is sdfstudio's code (its nerfstudio / scripts packages)."""
    name = sys._getframe(depth).f_globals.get("__name__", "")
    return name.partition(".")[0] in HOST_PACKAGES


@contextlib.contextmanager
def cpu_meaning() -> Iterator[None]:
    """While no CUDA device is available: for calls made by sdfstudio's code,
    ``torch.cuda.synchronize`` / ``set_device`` do nothing and ``Tensor.cuda()`` returns the tensor
    itself; every other caller gets torch's functions. With CUDA, nothing changes."""
    if torch.cuda.is_available():
        yield
        return
    saved = torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda
    real_sync, real_set, real_cuda = saved

    def synchronize(*args, **kwargs):
        return None if _from_host() else real_sync(*args, **kwargs)

    def set_device(*args, **kwargs):
        return None if _from_host() else real_set(*args, **kwargs)

    def cuda(self, *args, **kwargs):
        return self if _from_host() else real_cuda(self, *args, **kwargs)

    torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda = synchronize, set_device, cuda
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


class _CpuCuda(types.ModuleType):
    """``torch.cuda`` as the writer and ``scripts.train`` see it."""

    @staticmethod
    def synchronize(*args, **kwargs):
        if torch.cuda.is_available():
            return torch.cuda.synchronize(*args, **kwargs)
        return None

    @staticmethod
    def set_device(*args, **kwargs):
        if torch.cuda.is_available():
            return torch.cuda.set_device(*args, **kwargs)
        return None

    def __getattr__(self, name: str):
        return getattr(torch.cuda, name)


class _TorchView(types.ModuleType):
    """``torch`` as the writer and ``scripts.train`` see it: torch, but :class:`_CpuCuda` for ``cuda``."""

    cuda = _CpuCuda("torch.cuda", "torch.cuda for sdfstudio's writer and train loop (sp_plugins.patches.sdfstudio_cuda)")

    def __getattr__(self, name: str):
        return getattr(torch, name)


CPU_TORCH = _TorchView("torch", "torch for sdfstudio's writer and train loop (sp_plugins.patches.sdfstudio_cuda)")


def _torch_view(module, rebind) -> None:
    expect_attribute(PATCH, module, "torch")
    PATCH.expect(module.torch is torch or module.torch is CPU_TORCH, f"{module.__name__}.torch = torch",
                 f"{module.__name__}.torch = {module.torch!r}")
    rebind(module, "torch", CPU_TORCH)


MESH_FUNCTIONS = ("get_surface_sliding", "get_surface_sliding_with_contraction")


def _patch_marching_cubes(module, rebind) -> None:
    for name in MESH_FUNCTIONS:
        rebind(module, name, cpu_safe(expect_attribute(PATCH, module, name, ".cuda()")))


def _patch_extract_mesh(module, rebind) -> None:  # it imported the functions by name
    for name in MESH_FUNCTIONS:
        if hasattr(module, name):
            rebind(module, name, cpu_safe(getattr(module, name)))


PAIR_PARSERS = {
    "nerfstudio.data.dataparsers.sdfstudio_dataparser": "SDFStudio",
    "nerfstudio.data.dataparsers.monosdf_dataparser": "MonoSDFScene",
}


def _patch_parser(module, rebind) -> None:
    cls = expect_attribute(PATCH, module, PAIR_PARSERS[module.__name__])
    rebind(cls, "_generate_dataparser_outputs", cpu_safe(expect_attribute(PATCH, cls, "_generate_dataparser_outputs", ".cuda()")))


@contextlib.contextmanager
def cpu_safe_sdfstudio() -> Iterator[None]:
    after = {
        "nerfstudio.utils.writer": _torch_view,
        "scripts.train": _torch_view,
        "nerfstudio.utils.marching_cubes": _patch_marching_cubes,
        "scripts.extract_mesh": _patch_extract_mesh,
    }
    after.update({name: _patch_parser for name in PAIR_PARSERS})
    with patching(after=after):
        yield


SOURCES = {
    "nerfstudio/utils/writer.py": "torch.cuda.synchronize()",
    "scripts/train.py": "torch.cuda.set_device(local_rank)",
    "nerfstudio/utils/marching_cubes.py": ".cuda()",
    "nerfstudio/data/dataparsers/sdfstudio_dataparser.py": ".cuda()",
}


def _check(patch: Patch) -> None:
    for relative, snippet in SOURCES.items():
        expect_source(patch, relative, snippet)
    for attr in ("synchronize", "set_device"):
        patch.expect(callable(getattr(torch.cuda, attr, None)), f"torch.cuda.{attr}", f"torch.cuda.{attr} = {getattr(torch.cuda, attr, None)!r}")
    patch.expect(callable(getattr(torch.Tensor, "cuda", None)), "torch.Tensor.cuda", f"torch.Tensor.cuda = {getattr(torch.Tensor, 'cuda', None)!r}")


PATCH = sdfstudio_patch(
    "sdfstudio_cuda", _check, cpu_safe_sdfstudio, *SOURCES,
    guarded=(("torch.cuda", "synchronize"), ("torch.cuda", "set_device"), ("torch.Tensor", "cuda")),
    changes="writer's / scripts.train's `torch` -> a view with CPU cuda.synchronize/set_device; mesh functions and pair parsers: Tensor.cuda() stays put for sdfstudio's calls",
    scope_text="no CUDA only; those modules' own calls (Tensor.cuda: during the mesh / parser call); process-wide (those modules) in sp-sdfstudio-* / the hook")
