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

Registry entry ``nerfstudio_marching_cubes``, only on machines without CUDA, held by our SDF
models (``registry.hold``): from the build of one of them (``ns-export`` builds the model from the
saved config before it meshes) until the last one is garbage-collected, the name points at
:func:`scoped_marching_cubes`. That asks the callable it is given whether it evaluates one of our
SDF fields, through our field's own ``forward_geonetwork`` (which reports to
:func:`serving_mesher` while a one-point probe runs): only then does it mesh on the CPU; every
other SDF goes to nerfstudio's own mesher, so a method that is not ours behaves exactly as without
sp-plugins. With CUDA available nothing is installed. After the scope both names are nerfstudio's
function again.
"""

from __future__ import annotations

import importlib.metadata
import contextlib
import inspect
import logging
import sys
import threading
from typing import Any, Callable, Iterator, Optional, Tuple

import numpy as np
import torch

from sp_plugins.patches import registry
from sp_plugins.patches.registry import nerfstudio_patch

logger = logging.getLogger(__name__)

TESTED_NERFSTUDIO_VERSIONS: tuple[str, ...] = ("1.1.5",)
FUNCTION = "generate_mesh_with_multires_marching_cubes"
MODULES = ("nerfstudio.exporter.marching_cubes", "nerfstudio.scripts.exporter")

_originals: dict = {}


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
    from sp_plugins.geometry import sparse_extract_mesh  # defers trimesh and scikit-image to a mesh export

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
    original = _originals.get(MODULES[0], getattr(marching_cubes, FUNCTION, None))
    if original is scoped_marching_cubes:
        original = None
    expected = list(inspect.signature(cpu_marching_cubes).parameters)
    if not callable(original):
        PATCH.fail(f"{MODULES[0]}.{FUNCTION}{tuple(expected)}", f"{MODULES[0]}.{FUNCTION} = {original!r}")
    params = list(inspect.signature(original).parameters)
    PATCH.expect(params == expected, f"{FUNCTION}{tuple(expected)}", f"{FUNCTION}{tuple(params)}")
    return version


_probe = threading.local()


def serving_mesher(field: Any) -> None:
    """Called by our SDF fields' ``forward_geonetwork``: while :func:`evaluates_our_field` probes a
    callable, note that it reached one of ours (a ``getattr`` otherwise)."""
    fields = getattr(_probe, "fields", None)
    if fields is not None:
        fields.append(field)


def evaluates_our_field(fn: Callable[[torch.Tensor], torch.Tensor]) -> bool:
    """Whether ``fn`` (what ns-export hands the mesher: an SDF of points) evaluates one of our SDF
    fields: ``fn`` runs on one point, and our field's ``forward_geonetwork`` says so."""
    _probe.fields = []
    try:
        with torch.no_grad():
            fn(torch.zeros(1, 3))
    except Exception:  # noqa: BLE001  (a callable that cannot run on one CPU point is not ours)
        pass
    finally:
        found = _probe.__dict__.pop("fields", [])
    return bool(found)


def scoped_marching_cubes(*args: Any, **kwargs: Any):
    """nerfstudio's mesher, except for an SDF of one of our fields: :func:`cpu_marching_cubes`. Takes
    the arguments of both (the guard holds their signatures equal) and hands them on positionally."""
    bound = inspect.signature(cpu_marching_cubes).bind(*args, **kwargs)
    bound.apply_defaults()
    if evaluates_our_field(bound.args[0]):
        return cpu_marching_cubes(*bound.args)
    return _originals[MODULES[0]](*bound.args)


scoped_marching_cubes.__signature__ = inspect.signature(cpu_marching_cubes)  # type: ignore[attr-defined]


@contextlib.contextmanager
def cpu_mesher_for_our_fields(force: bool = False) -> Iterator[bool]:
    """Both names point at :func:`scoped_marching_cubes` for the block when CUDA is unavailable (or
    ``force``); yields whether they do. After it they are nerfstudio's function again."""
    if torch.cuda.is_available() and not force:
        yield False
        return
    import nerfstudio.exporter.marching_cubes as host

    original = getattr(host, FUNCTION)
    _originals[MODULES[0]] = original
    for name in MODULES:
        module = sys.modules.get(name)
        if module is not None:
            setattr(module, FUNCTION, scoped_marching_cubes)
    try:
        yield True
    finally:
        for name in MODULES:  # (also a module that imported the name inside the block)
            module = sys.modules.get(name)
            if module is not None and getattr(module, FUNCTION, None) is scoped_marching_cubes:
                setattr(module, FUNCTION, original)
        _originals.pop(MODULES[0], None)


def hold_for(model: Any, force: bool = False) -> bool:
    """Our SDF model ``model`` holds the CPU mesher while it exists (no CUDA, or ``force``)."""
    if torch.cuda.is_available() and not force:
        return False
    registry.hold(PATCH.name, model, force=force)
    return True


PATCH = nerfstudio_patch(
    "nerfstudio_marching_cubes", TESTED_NERFSTUDIO_VERSIONS, lambda patch: check_nerfstudio_marching_cubes() and None,
    cpu_mesher_for_our_fields, ((MODULES[0], FUNCTION),),
    changes=f"{MODULES[0]}.{FUNCTION} and its import in {MODULES[1]}: our CPU mesher for an SDF that evaluates our field",
    scope_text="without CUDA only: while one of our SDF models exists (ns-export builds it, then meshes)")
