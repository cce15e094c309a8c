"""Marching cubes at high resolution without a dense grid: coarse to fine, only near the surface.

A learned SDF is expensive to query (a hash grid and an MLP per point), and almost all of a
``512^3`` grid is far from the surface. :func:`sparse_extract_mesh` evaluates a coarse grid
first and refines, level by level (each halving the cell size), only the cells that can hold the
surface: a sign change at their corners, or a corner value within ``margin`` cell diagonals of
the level (an SDF with ``|grad f| <= margin`` cannot cross zero in a cell whose corners are all
farther than that). The finest cells are meshed brick by brick with scikit-image's marching
cubes, and the bricks' shared vertices are welded exactly.

Grid points that were never evaluated lie in cells that were ruled out at some level; their value
is the trilinear interpolation of the coarser level, which keeps the sign of those cells and so
adds no surface. The assumption is the Lipschitz bound: a surface thinner than a coarse cell whose
field stays farther than ``margin`` diagonals from zero at every corner is missed (raise
``margin`` or ``coarse`` for such fields; a field that is near zero everywhere is simply evaluated
densely, with a progress bar).
"""

from __future__ import annotations

import logging
import math
from typing import Callable, Optional, Union

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from torch import Tensor

from sp_plugins.geometry.marching_cubes import BoundsLike, SDFFunction, _as_box, _query

log = logging.getLogger(__name__)

_CORNERS = np.array([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], dtype=np.int64)


def coarse_levels(resolution: int, coarse: int = 32) -> tuple[int, int]:
    """``(levels, coarse_cells)``: the number of halvings from a grid of about ``coarse`` cells
    per axis up to ``resolution`` cells (``coarse_cells * 2**levels >= resolution``)."""
    if resolution < 1:
        raise ValueError(f"resolution={resolution}: must be >= 1 cell per axis")
    levels = max(0, int(math.floor(math.log2(max(resolution / max(coarse, 1), 1.0)))))
    return levels, int(math.ceil(resolution / 2**levels))


class _LevelStore:
    """Field values at the evaluated points of one level's grid, keyed by linear index."""

    def __init__(self, points_per_axis: int):
        self.n = points_per_axis
        self.keys = np.empty(0, dtype=np.int64)
        self.values = np.empty(0, dtype=np.float32)

    def key(self, ijk: np.ndarray) -> np.ndarray:
        return (ijk[..., 0] * self.n + ijk[..., 1]) * self.n + ijk[..., 2]

    def ijk(self, keys: np.ndarray) -> np.ndarray:
        return np.stack(np.unravel_index(keys, (self.n,) * 3), axis=-1)

    def add(self, keys: np.ndarray, values: np.ndarray) -> None:
        keys = np.concatenate([self.keys, keys])
        values = np.concatenate([self.values, values.astype(np.float32)])
        order = np.argsort(keys, kind="stable")
        self.keys, self.values = keys[order], values[order]

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(found, values)`` for ``keys`` (values are 0 where not found)."""
        if len(self.keys) == 0:
            return np.zeros(keys.shape, bool), np.zeros(keys.shape, np.float32)
        pos = np.clip(np.searchsorted(self.keys, keys), 0, len(self.keys) - 1)
        found = self.keys[pos] == keys
        return found, np.where(found, self.values[pos], 0.0).astype(np.float32)

    def missing(self, keys: np.ndarray) -> np.ndarray:
        return keys[~self.lookup(keys)[0]]


def _evaluate(sdf_fn: SDFFunction, ijk: np.ndarray, lo: np.ndarray, spacing: float, level: float,
              chunk: int, device, dtype, bar) -> np.ndarray:
    out = np.empty(len(ijk), dtype=np.float32)
    for start in range(0, len(ijk), chunk):
        sl = slice(start, start + chunk)
        out[sl] = _query(sdf_fn, lo + ijk[sl] * spacing, device, dtype) - level
        if bar is not None:
            bar.update(len(out[sl]))
    # an exact zero at a grid point shared by two bricks can be meshed differently by each:
    # count it as outside (the vertex lands on the point either way)
    out[out == 0] = np.finfo(np.float32).tiny
    return out


def _active(corner_values: np.ndarray, threshold: float) -> np.ndarray:
    """``[m, 8]`` corner values -> ``[m]`` cells that can hold the zero set."""
    crosses = (corner_values.min(1) <= 0) & (corner_values.max(1) >= 0)
    return crosses | (np.abs(corner_values).min(1) <= threshold)


def sparse_extract_mesh(
    sdf_fn: SDFFunction,
    bounds: BoundsLike = (-1.0, 1.0),
    resolution: int = 512,
    *,
    level: float = 0.0,
    coarse: int = 32,
    margin: float = 1.5,
    brick: int = 32,
    chunk: int = 1 << 17,
    device: Union[str, torch.device] = "cpu",
    dtype: torch.dtype = torch.float32,
    progress: bool = True,
    on_level: Optional[Callable[[int, int, int], None]] = None,
) -> trimesh.Trimesh:
    """Mesh of the ``level`` set of ``sdf_fn`` (negative inside, normals outward) on a
    ``resolution``-cell grid over ``bounds`` (cubic cells of the box's largest side), evaluating
    the field only near the surface.

    Args:
        resolution: cells along the box's longest axis (any value >= 1; the grid points are
            ``resolution + 1``).
        coarse: cells per axis of the first, dense level (about; levels halve the cell size).
        margin: a cell is refined when a corner value is within ``margin`` cell diagonals of the
            level, or its corners change sign (the assumed bound on ``|grad f|``).
        brick: finest cells per brick handed to scikit-image at once.
        progress: a tqdm bar per level on stderr.
        on_level: ``on_level(level, cells_per_axis, points_evaluated)`` after each level.

    Returns:
        a ``trimesh.Trimesh`` in the coordinates of ``bounds`` (empty when nothing crosses).
    """
    from skimage.measure import marching_cubes
    from tqdm.auto import tqdm

    lo, hi = _as_box(bounds)
    if resolution < 2:
        raise ValueError(f"resolution={resolution}: need at least 2 cells per axis")
    if margin < 0:
        raise ValueError(f"margin={margin}: must be >= 0")
    spacing_fine = float((hi - lo).max() / resolution)
    cells_fine = np.ceil((hi - lo) / spacing_fine - 1e-9).astype(np.int64)  # per axis, <= resolution
    levels, coarse_cells = coarse_levels(resolution, coarse)
    brick = max(int(brick), 2**levels)
    brick = int(2 ** math.ceil(math.log2(brick)))

    stores: list[_LevelStore] = []
    active: Optional[np.ndarray] = None  # [m, 3] active cells of the current level
    for lev in range(levels + 1):
        n_cells = coarse_cells * 2**lev
        store = _LevelStore(n_cells + 1)
        spacing = spacing_fine * 2 ** (levels - lev)
        if lev == 0:
            axes = np.arange(n_cells + 1)
            ijk = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), -1).reshape(-1, 3)
            cells = np.stack(np.meshgrid(*(np.arange(n_cells),) * 3, indexing="ij"), -1).reshape(-1, 3)
            # drop the padding cells beyond the box on its shorter axes
            limit = np.ceil(cells_fine / 2**levels).astype(np.int64)
            ijk = ijk[(ijk <= limit).all(1)]
            cells = cells[(cells < limit).all(1)]
            need = store.key(ijk)
        else:
            prev = stores[-1]
            assert active is not None  # the coarser level's cells (the loop stops at a level that kept none)
            # points shared with the coarser level are known already
            store.add(store.key(prev.ijk(prev.keys) * 2), prev.values)
            cells = (active[:, None, :] * 2 + _CORNERS[None]).reshape(-1, 3)
            limit = np.ceil(cells_fine / 2 ** (levels - lev)).astype(np.int64)
            cells = cells[(cells < limit).all(1)]
            need = np.unique(store.key((cells[:, None, :] + _CORNERS[None]).reshape(-1, 3)))
            need = store.missing(need)
        bar = tqdm(total=len(need), desc=f"marching cubes {resolution}^3: level {lev + 1}/{levels + 1} ({n_cells}^3)",
                   unit="pt", unit_scale=True, leave=False, disable=not progress, mininterval=1.0)
        values = _evaluate(sdf_fn, store.ijk(need), lo, spacing, level, chunk, device, dtype, bar)
        bar.close()
        bad = ~np.isfinite(values)
        if bad.any():
            raise ValueError(f"the field is NaN or inf at {int(bad.sum())} of {len(values)} grid points; the fit diverged or sdf_fn is wrong")
        store.add(need, values)
        stores.append(store)
        _, corner_values = store.lookup(store.key(cells[:, None, :] + _CORNERS[None]))
        threshold = margin * spacing * math.sqrt(3.0) if lev < levels else 0.0
        active = cells[_active(corner_values, threshold)]
        log.info("marching cubes level %d/%d: %d^3 cells, %d points evaluated, %d cells kept",
                 lev + 1, levels + 1, n_cells, len(need), len(active))
        if on_level is not None:
            on_level(lev, n_cells, len(need))
        if len(active) == 0:
            break

    if active is None or len(active) == 0 or len(stores) < levels + 1:
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)

    bricks = np.unique(active // brick, axis=0)
    all_verts, all_faces, offset = [], [], 0
    for b in bricks:
        volume = _brick_volume(stores, b, brick, levels)
        end = np.minimum(brick, cells_fine - b * brick)  # crop at the box
        volume = volume[: end[0] + 1, : end[1] + 1, : end[2] + 1]
        if not (volume.min() < 0 < volume.max()) or min(volume.shape) < 2:
            continue
        verts, faces, _, _ = marching_cubes(volume, level=0.0, gradient_direction="descent")
        all_verts.append(verts.astype(np.float64) + b * brick)
        all_faces.append(faces + offset)
        offset += len(verts)
    if not all_verts:
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)
    verts = np.concatenate(all_verts)
    faces = np.concatenate(all_faces)
    # bricks share their boundary faces: the same edge gives bit-identical vertices in both
    verts, inverse = np.unique(verts, axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return trimesh.Trimesh(vertices=lo + verts * spacing_fine, faces=faces[keep], process=False)


def _brick_volume(stores: list, brick_index: np.ndarray, brick: int, levels: int) -> Float[np.ndarray, "b b b"]:
    """Values on the ``(brick + 1)^3`` finest grid points of one brick: each level's known values
    over the trilinear upsampling of the coarser level."""
    volume: Optional[Tensor] = None
    for lev, store in enumerate(stores):
        scale = 2 ** (levels - lev)
        size = brick // scale
        origin = brick_index * size
        axes = [np.arange(origin[a], origin[a] + size + 1) for a in range(3)]
        ijk = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
        inside = (ijk < store.n).all(-1)
        found, values = store.lookup(store.key(np.minimum(ijk, store.n - 1)))
        found &= inside
        if volume is None:
            volume = torch.from_numpy(values)
        else:
            volume = torch.nn.functional.interpolate(volume[None, None], size=(size + 1,) * 3, mode="trilinear",
                                                     align_corners=True)[0, 0]
            volume = torch.where(torch.from_numpy(found), torch.from_numpy(values), volume)
    assert volume is not None  # stores holds every level, the coarsest first
    return volume.numpy()
