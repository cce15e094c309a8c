"""Let ``ns-export marching-cubes`` run without CUDA.

Targets nerfstudio 1.1.5 (see ``TESTED_NERFSTUDIO_VERSIONS``). There,
``nerfstudio.exporter.marching_cubes.generate_mesh_with_multires_marching_cubes`` moves its query
points to the GPU with ``.cuda()`` unconditionally, so ``ns-export marching-cubes`` fails on a
CPU-only machine for every SDF method. ``nerfstudio.scripts.exporter`` imports that function by
name. The patch rebinds that name (in both modules, where loaded) to :func:`cpu_marching_cubes`,
which evaluates the field on the CPU in a narrow band around the surface (a coarse grid first,
full resolution only where the surface can be) and meshes it with scikit-image.

It is explicit and only for machines without CUDA: our SDF models call
:func:`install_cpu_marching_cubes` when they are built (``ns-export`` builds the model from the
saved config before it meshes). With CUDA available it does nothing.
"""

from __future__ import annotations

import importlib.metadata
import inspect
import logging
import sys
from typing import Callable, Optional, Tuple

import numpy as np
import torch

logger = logging.getLogger(__name__)

TESTED_NERFSTUDIO_VERSIONS: tuple[str, ...] = ("1.1.5",)
FUNCTION = "generate_mesh_with_multires_marching_cubes"
MODULES = ("nerfstudio.exporter.marching_cubes", "nerfstudio.scripts.exporter")

_originals: dict = {}


COARSE_FACTOR = 8
"""Fine grid cells per coarse cell along each axis in the narrow-band search."""


def _shifted_or(cells: np.ndarray) -> np.ndarray:
    """Grid points touched by any marked cell: ``[n, n, n]`` cells -> ``[n+1, n+1, n+1]`` points."""
    n = cells.shape[0]
    points = np.zeros((n + 1,) * 3, dtype=bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                points[dx : dx + n, dy : dy + n, dz : dz + n] |= cells
    return points


def narrow_band_volume(
    sdf_fn: Callable[[torch.Tensor], torch.Tensor],
    resolution: int,
    lo: np.ndarray,
    hi: np.ndarray,
    level: float = 0.0,
    chunk: int = 1 << 18,
) -> np.ndarray:
    """The field on a ``(resolution + 1)^3`` grid, evaluated exactly only near the ``level`` set.

    A grid ``COARSE_FACTOR`` times coarser is evaluated first. Coarse cells whose corner values
    straddle ``level``, or come within two cell diagonals of it (an SDF changes by at most its
    distance), and their neighbours are evaluated at full resolution; elsewhere the fine grid holds
    the coarse grid interpolated trilinearly, which keeps the sign there and so adds no surface.
    """
    from scipy.ndimage import binary_dilation

    from sp_plugins.geometry import evaluate_grid

    if resolution % COARSE_FACTOR:
        raise ValueError(f"resolution={resolution}: must be a multiple of {COARSE_FACTOR}")
    n_coarse = resolution // COARSE_FACTOR
    coarse = evaluate_grid(sdf_fn, (lo, hi), n_coarse + 1, chunk=chunk).astype(np.float32) - level
    corners = np.stack([coarse[dx : dx + n_coarse, dy : dy + n_coarse, dz : dz + n_coarse]
                        for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])
    band = 2.0 * float(np.linalg.norm((hi - lo) / n_coarse))
    near = (corners.min(0) <= band) & (corners.max(0) >= -band)
    near = binary_dilation(near, iterations=1)
    fine = torch.nn.functional.interpolate(
        torch.from_numpy(coarse)[None, None], size=(resolution + 1,) * 3, mode="trilinear", align_corners=True
    )[0, 0].numpy()
    cells = np.kron(near, np.ones((COARSE_FACTOR,) * 3, dtype=bool)).astype(bool)
    idx = np.nonzero(_shifted_or(cells))
    del cells
    spacing = (hi - lo) / resolution
    values = np.empty(len(idx[0]), dtype=np.float32)
    for start in range(0, len(values), chunk):
        sl = slice(start, start + chunk)
        pts = lo + np.stack([idx[0][sl], idx[1][sl], idx[2][sl]], axis=-1) * spacing
        with torch.no_grad():
            out = sdf_fn(torch.as_tensor(pts, dtype=torch.float32)).reshape(-1)
        values[sl] = out.detach().cpu().numpy() - level
    fine[idx] = values
    logger.info("narrow band: %d of %d grid points evaluated", len(values), fine.size)
    return fine


def cpu_marching_cubes(
    geometry_callable_field: Callable[[torch.Tensor], torch.Tensor],
    resolution: int = 1024,
    bounding_box_min: Tuple[float, float, float] = (-1.0, -1.0, -1.0),
    bounding_box_max: Tuple[float, float, float] = (1.0, 1.0, 1.0),
    isosurface_threshold: float = 0.0,
    coarse_mask: Optional[torch.Tensor] = None,
):
    """Drop-in for nerfstudio's mesher (same arguments, returns a ``trimesh.Trimesh``): a
    ``resolution``^3 grid evaluated on the CPU in a narrow band around the surface, meshed with
    scikit-image (faces oriented outward for an SDF that is negative inside)."""
    import trimesh
    from skimage.measure import marching_cubes

    if coarse_mask is not None:
        raise ValueError("coarse_mask is not supported by sp_plugins' CPU marching cubes; pass None")
    lo = np.asarray(bounding_box_min, dtype=np.float64)
    hi = np.asarray(bounding_box_max, dtype=np.float64)
    logger.info("marching cubes on the CPU at %d^3 (sp_plugins patch; nerfstudio's mesher needs CUDA)", resolution)
    volume = narrow_band_volume(geometry_callable_field, resolution, lo, hi, isosurface_threshold)
    if not (volume.min() < 0 < volume.max()):
        raise ValueError(f"the field does not cross {isosurface_threshold} inside the box {lo.tolist()}..{hi.tolist()}: no surface to mesh")
    spacing = tuple((hi - lo) / resolution)
    verts, faces, _, _ = marching_cubes(volume, level=0.0, spacing=spacing, gradient_direction="descent")
    return trimesh.Trimesh(vertices=verts + lo, faces=faces, process=False)


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


def install_cpu_marching_cubes(force: bool = False) -> bool:
    """Rebind nerfstudio's mesher to :func:`cpu_marching_cubes` when CUDA is unavailable (or
    ``force``). Returns True when the patch is in place. Idempotent."""
    if torch.cuda.is_available() and not force:
        return False
    check_nerfstudio_marching_cubes()
    import nerfstudio.exporter.marching_cubes  # noqa: F401  (load it so both names are patched)

    for name in MODULES:
        module = sys.modules.get(name)
        if module is None or getattr(module, FUNCTION, None) is cpu_marching_cubes:
            continue
        _originals.setdefault(name, getattr(module, FUNCTION))
        setattr(module, FUNCTION, cpu_marching_cubes)
    return True


def uninstall_cpu_marching_cubes() -> None:
    for name, original in list(_originals.items()):
        module = sys.modules.get(name)
        if module is not None:
            setattr(module, FUNCTION, original)
        del _originals[name]
