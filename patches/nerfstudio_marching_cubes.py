"""Let ``ns-export marching-cubes`` run without CUDA.

Targets nerfstudio 1.1.5 (see ``TESTED_NERFSTUDIO_VERSIONS``). There,
``nerfstudio.exporter.marching_cubes.generate_mesh_with_multires_marching_cubes`` moves its query
points to the GPU with ``.cuda()`` unconditionally, so ``ns-export marching-cubes`` fails on a
CPU-only machine for every SDF method. ``nerfstudio.scripts.exporter`` imports that function by
name. The patch rebinds that name (in both modules, where loaded) to :func:`cpu_marching_cubes`,
which evaluates the field on the CPU coarse to fine, only near the surface, and meshes it with
scikit-image (:mod:`sp_plugins.geometry.sparse_marching_cubes`): a 512^3 mesh of a NeuS field
takes minutes instead of an unknown time. ``ns-export marching-cubes`` itself still asks for a
resolution divisible by 512 and textures the mesh afterwards; ``sp-export-mesh`` meshes at any
resolution without texturing.

It is explicit, only for machines without CUDA, and scoped to our models: our SDF models call
:func:`claim_for_cpu_marching_cubes` when they are built (``ns-export`` builds the model from the
saved config before it meshes). The name then points at :func:`scoped_marching_cubes`, which
meshes on the CPU only when the SDF it is given belongs to a claimed model (the exporter passes a
closure over its pipeline) and calls nerfstudio's own mesher for everything else, so a method that
is not ours behaves exactly as without sp-plugins. With CUDA available nothing is installed.
"""

from __future__ import annotations

import importlib.metadata
import inspect
import logging
import sys
import weakref
from typing import Any, Callable, Optional, Tuple

import numpy as np
import torch

logger = logging.getLogger(__name__)

TESTED_NERFSTUDIO_VERSIONS: tuple[str, ...] = ("1.1.5",)
FUNCTION = "generate_mesh_with_multires_marching_cubes"
MODULES = ("nerfstudio.exporter.marching_cubes", "nerfstudio.scripts.exporter")

_originals: dict = {}
_claimed: "weakref.WeakSet[Any]" = weakref.WeakSet()


def cpu_marching_cubes(
    geometry_callable_field: Callable[[torch.Tensor], torch.Tensor],
    resolution: int = 1024,
    bounding_box_min: Tuple[float, float, float] = (-1.0, -1.0, -1.0),
    bounding_box_max: Tuple[float, float, float] = (1.0, 1.0, 1.0),
    isosurface_threshold: float = 0.0,
    coarse_mask: Optional[torch.Tensor] = None,
):
    """Drop-in for nerfstudio's mesher (same arguments, returns a ``trimesh.Trimesh``): a
    ``resolution``^3 grid evaluated on the CPU, coarse to fine and only near the surface
    (:func:`sp_plugins.geometry.sparse_extract_mesh`), meshed with scikit-image brick by brick
    (faces oriented outward for an SDF that is negative inside), with a progress bar per level."""
    from sp_plugins.geometry import sparse_extract_mesh

    if coarse_mask is not None:
        raise ValueError("coarse_mask is not supported by sp_plugins' CPU marching cubes; pass None")
    lo = np.asarray(bounding_box_min, dtype=np.float64)
    hi = np.asarray(bounding_box_max, dtype=np.float64)
    logger.info("marching cubes on the CPU at %d^3 (sp_plugins patch; nerfstudio's mesher needs CUDA)", resolution)
    mesh = sparse_extract_mesh(geometry_callable_field, (lo, hi), resolution, level=isosurface_threshold)
    if len(mesh.faces) == 0:
        raise ValueError(f"the field does not cross {isosurface_threshold} inside the box {lo.tolist()}..{hi.tolist()}: no surface to mesh")
    return mesh


def check_nerfstudio_marching_cubes() -> str:
    """Verify the nerfstudio code the patch replaces; return the nerfstudio version."""
    from nerfstudio.exporter import marching_cubes

    version = importlib.metadata.version("nerfstudio")
    problems = []
    original = _originals.get(MODULES[0], getattr(marching_cubes, FUNCTION, None))
    if original is None:
        problems.append(f"{MODULES[0]} has no {FUNCTION}")
    else:
        params = list(inspect.signature(original).parameters)
        expected = list(inspect.signature(cpu_marching_cubes).parameters)
        if params != expected:
            problems.append(f"{FUNCTION} takes {params}, the patch expects {expected}")
    if problems:
        raise RuntimeError(
            f"sp_plugins' CPU marching-cubes patch targets nerfstudio {', '.join(TESTED_NERFSTUDIO_VERSIONS)}; "
            f"installed nerfstudio {version} differs: " + "; ".join(problems) + ". Update patches/nerfstudio_marching_cubes.py."
        )
    return version


def _claimed_owner(fn: Callable) -> bool:
    """True when ``fn`` (the exporter's closure over its pipeline, or a bound method) reaches a
    claimed model."""
    candidates = [getattr(fn, "__self__", None)]
    for cell in getattr(fn, "__closure__", None) or ():
        try:
            candidates.append(cell.cell_contents)
        except ValueError:  # an empty cell
            continue
    for obj in candidates:
        for candidate in (obj, getattr(obj, "model", None)):
            try:
                if candidate is not None and candidate in _claimed:
                    return True
            except TypeError:  # unhashable
                continue
    return False


def scoped_marching_cubes(
    geometry_callable_field: Callable[[torch.Tensor], torch.Tensor],
    resolution: int = 1024,
    bounding_box_min: Tuple[float, float, float] = (-1.0, -1.0, -1.0),
    bounding_box_max: Tuple[float, float, float] = (1.0, 1.0, 1.0),
    isosurface_threshold: float = 0.0,
    coarse_mask: Optional[torch.Tensor] = None,
):
    """nerfstudio's mesher, except for the SDF of a claimed model: :func:`cpu_marching_cubes`."""
    args = (geometry_callable_field, resolution, bounding_box_min, bounding_box_max, isosurface_threshold, coarse_mask)
    if _claimed_owner(geometry_callable_field):
        return cpu_marching_cubes(*args)
    return _originals[MODULES[0]](*args)


def claim_for_cpu_marching_cubes(model: Any, force: bool = False) -> bool:
    """Mesh ``model``'s SDF on the CPU under ``ns-export marching-cubes`` (no CUDA, or ``force``);
    every other model keeps nerfstudio's mesher. True when the claim is in place."""
    if not install_cpu_marching_cubes(force):
        return False
    _claimed.add(model)
    return True


def install_cpu_marching_cubes(force: bool = False) -> bool:
    """Rebind nerfstudio's mesher to :func:`scoped_marching_cubes` when CUDA is unavailable (or
    ``force``). Returns True when the patch is in place. Idempotent."""
    if torch.cuda.is_available() and not force:
        return False
    check_nerfstudio_marching_cubes()
    import nerfstudio.exporter.marching_cubes  # noqa: F401  (load it so both names are patched)

    for name in MODULES:
        module = sys.modules.get(name)
        if module is None or getattr(module, FUNCTION, None) is scoped_marching_cubes:
            continue
        _originals.setdefault(name, getattr(module, FUNCTION))
        setattr(module, FUNCTION, scoped_marching_cubes)
    return True


def uninstall_cpu_marching_cubes() -> None:
    for name, original in list(_originals.items()):
        module = sys.modules.get(name)
        if module is not None:
            setattr(module, FUNCTION, original)
        del _originals[name]
