"""Render a mesh into a small multi-view dataset: Blender and SDFStudio layouts plus the true mesh.

``make_scene(mesh, out_dir)`` writes::

    out_dir/scene.json     normalisation (centre, scale, up axis), scene box, cameras, splits
    out_dir/gt_mesh.ply    the normalised mesh, in dataset coordinates (for Chamfer)
    out_dir/blender/       transforms_{train,val,test}.json + RGBA PNGs   (nerfstudio: blender-data)
    out_dir/sdfstudio/     meta_data.json (+ _val, _test) + RGB + masks    (nerfstudio: sdfstudio-data)

Dataset coordinates are shared by both layouts: the mesh fits a sphere of radius ``radius``
(0.85) at the origin, inside the scene box [-1, 1]^3; cameras sit at ``camera_distance`` (4.0,
inside the near/far range 2..6 that nerfstudio's Blender models use) looking at the origin.
See `sp_plugins.data.coords` for how these map into nerfstudio's coordinates.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from sp_plugins.data.cameras import (
    balanced_directions,
    default_fov,
    intrinsics,
    look_at_origin,
    random_directions,
)
from sp_plugins.adapter.checks import existing_outputs
from sp_plugins.data.dtu_like import (
    BACKDROP_RADIUS,
    GROUND_HALF_SIZE,
    CapCameras,
    default_dtu_resolution,
    dtu_like_fov,
    render_dtu_views,
    surroundings,
)
from sp_plugins.data.layouts import write_blender, write_object_masks, write_sdfstudio
from sp_plugins.data.mesh import MeshSource, load_mesh, normalize_mesh, up_rotation
from sp_plugins.data.render import ray_intersector, render_views

LAYOUTS = ("blender", "sdfstudio")
SCENE_BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
NB_BLENDER_LOADER = "nerfbaselines.datasets.blender:load_blender_dataset"


def nerfbaselines_info(mesh: Any, box: Any) -> dict:
    """The Blender layout's ``nb-info.json``: nerfbaselines loads it with its own Blender loader as
    dataset ``sp-scene`` (registered by sp_plugins.nerfbaselines), scene = the mesh's name."""
    name = Path(str(mesh)).stem if not hasattr(mesh, "faces") else "mesh"
    return {"loader": NB_BLENDER_LOADER, "id": "sp-scene", "scene": name, "type": "object-centric",
            "evaluation_protocol": "sp-scene",
            "scene_box": [list(map(float, corner)) for corner in box]}
SCENE_FILE = "scene.json"
GT_MESH_FILE = "gt_mesh.ply"
PRODUCTS = (SCENE_FILE, GT_MESH_FILE, *LAYOUTS)
"""Every name `make_scene` writes inside ``out_dir``; nothing else there is touched."""


class SceneExistsError(FileExistsError, ValueError):
    """``out_dir`` already holds a scene and ``overwrite`` was not given."""


@dataclass(frozen=True)
class ScenePaths:
    """Where `make_scene` put things; a layout that was not requested is None."""

    root: Path
    scene_json: Path
    gt_mesh: Path
    blender: Optional[Path]
    sdfstudio: Optional[Path]


def _resolution(resolution: Union[int, Tuple[int, int]]) -> Tuple[int, int]:
    width, height = (resolution, resolution) if isinstance(resolution, (int, np.integer)) else tuple(resolution)
    if int(width) < 4 or int(height) < 4:
        raise ValueError(f"resolution must be at least 4x4 pixels, got {width}x{height}.")
    return int(width), int(height)


def _check_counts(n_train: int, n_val: int, n_test: int) -> None:
    for name, count in (("n_train", n_train), ("n_val", n_val), ("n_test", n_test)):
        if int(count) < 1:
            raise ValueError(f"{name} must be >= 1 (nerfstudio's parsers read every split), got {count}.")


def _prepare(out_dir: Path, overwrite: bool) -> None:
    existing = existing_outputs(out_dir, PRODUCTS, "output")
    if existing and not overwrite:
        raise SceneExistsError(
            f"{out_dir} already holds a scene ({', '.join(existing)}): pass overwrite=True (sp-scene --overwrite) "
            "to replace it, or choose another output directory."
        )
    for name in existing:
        target = out_dir / name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        else:
            target.unlink()
    out_dir.mkdir(parents=True, exist_ok=True)


def make_scene(
    mesh: MeshSource,
    out_dir: Union[str, Path],
    *,
    n_train: int = 24,
    n_val: int = 4,
    n_test: int = 4,
    resolution: Optional[Union[int, Tuple[int, int]]] = None,
    layouts: Sequence[str] = LAYOUTS,
    seed: int = 0,
    hemisphere: bool = False,
    up_axis: str = "z",
    radius: float = 0.85,
    camera_distance: float = 4.0,
    fov_x: Optional[float] = None,
    supersample: int = 2,
    backend: str = "auto",
    overwrite: bool = False,
    progress: bool = False,
    dtu_like: bool = False,
    cap: Optional[CapCameras] = None,
) -> ScenePaths:
    """Render `mesh` from cameras on a sphere into `out_dir` in the requested `layouts`.

    Args:
        mesh: a `trimesh.Trimesh`, a mesh file, ``"spot"`` (bundled) or a primitive name
            (``"sphere"``, ``"box"``, ``"torus"``, ``"capsule"``).
        n_train, n_val, n_test: views per split. Training cameras come in opposite-azimuth pairs
            (see `balanced_directions`); held-out cameras are drawn independently.
        resolution: image width = height, or ``(width, height)`` (default 64, or 96x72 with `dtu_like`).
        seed: all cameras are a deterministic function of it.
        hemisphere: keep cameras above the horizon (z >= 0) instead of the whole sphere.
        up_axis: the mesh axis that becomes +Z ('y' for most Y-up models).
        radius: the normalised mesh fits a sphere of this radius at the origin.
        camera_distance: distance of every camera from the origin.
        fov_x: horizontal field of view in radians; by default it frames the radius-`radius`
            sphere with a 15% margin.
        supersample: s*s rays per pixel (anti-aliased colours and fractional alpha).
        backend: ray caster, 'auto' | 'embree' | 'triangle' (see `render.ray_intersector`).
        overwrite: replace a scene already in `out_dir` (only the files this function writes).
        progress: show a tqdm bar while rendering.
        dtu_like: the object stands on a textured ground inside a textured backdrop, seen by cameras
            on a frontal cap (`cap`); images are opaque (no masks for training) and each layout gets
            ``object_mask/`` for metrics (see `sp_plugins.data.dtu_like`). `hemisphere` does not apply.
        cap: where the DTU-like cameras sit (default `CapCameras()`: 100 degrees of azimuth, 12-55
            degrees of elevation).
    """
    layouts = tuple(layouts)
    unknown = sorted(set(layouts) - set(LAYOUTS))
    if unknown or not layouts:
        raise ValueError(f"layouts must be a non-empty subset of {LAYOUTS}, got {layouts}.")
    _check_counts(n_train, n_val, n_test)
    if cap is not None and not dtu_like:
        raise ValueError("cap (the DTU-like camera cap) applies only with dtu_like=True (sp-scene --dtu-like).")
    if dtu_like and hemisphere:
        raise ValueError("hemisphere does not apply to a DTU-like scene: its cameras are on a frontal cap (see cap).")
    width, height = _resolution(default_dtu_resolution(resolution) if dtu_like else (64 if resolution is None else resolution))
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}.")
    if fov_x is not None:
        fov = float(fov_x)
    else:
        fov = dtu_like_fov(radius, camera_distance, width, height) if dtu_like else default_fov(radius, camera_distance)
    if not 0.0 < fov < math.pi:
        raise ValueError(f"fov_x must be in (0, pi) radians, got {fov}.")
    source = load_mesh(mesh)
    normalised, center, scale = normalize_mesh(source, radius=radius, up_axis=up_axis)
    out_dir = Path(out_dir).expanduser()
    _prepare(out_dir, overwrite)

    rng = np.random.default_rng(seed)
    if dtu_like:
        cap = cap or CapCameras()
        directions = {"train": cap.grid(n_train, rng), "val": cap.random(n_val, rng), "test": cap.random(n_test, rng)}
    else:
        directions = {
            "train": balanced_directions(n_train, rng, hemisphere),
            "val": random_directions(n_val, rng, hemisphere),
            "test": random_directions(n_test, rng, hemisphere),
        }
    K = intrinsics(width, height, fov)
    caster = None if dtu_like else ray_intersector(normalised, backend)
    views, object_masks = {}, {}
    for split, dirs in directions.items():
        c2w = look_at_origin(camera_distance * dirs)
        if dtu_like:
            rgb, object_masks[split] = render_dtu_views(
                normalised, c2w, K, width, height, supersample=supersample, backend=backend, progress=progress,
                desc=f"rendering {split}",
            )
            images = np.concatenate([rgb, np.ones_like(rgb[..., :1])], axis=-1)  # opaque: nothing to mask out
        else:
            images = render_views(
                normalised, c2w, K, width, height, supersample, progress=progress, intersector=caster, desc=f"rendering {split}"
            )
        views[split] = (c2w, images)

    # x_dataset = (R_up x_mesh - center) * scale  <=>  x_mesh = R_up^T (x_dataset / scale + center)
    dataset_to_mesh = np.eye(4)
    dataset_to_mesh[:3, :3] = np.eye(3) / scale
    dataset_to_mesh[:3, 3] = center
    dataset_to_mesh = up_rotation(up_axis).T @ dataset_to_mesh

    gt_mesh = out_dir / GT_MESH_FILE
    normalised.export(gt_mesh)
    # every camera is camera_distance from the origin: [near, far] holds the whole box (half-diagonal
    # sqrt(3)) along every ray, so the SDFStudio layout's near_far collider never cuts the object
    near, far = max(camera_distance - math.sqrt(3.0), 0.05), camera_distance + math.sqrt(3.0)
    paths = {"blender": None, "sdfstudio": None}
    if "blender" in layouts:
        paths["blender"] = out_dir / "blender"
        write_blender(paths["blender"], views, fov, nb_info=nerfbaselines_info(mesh, SCENE_BOX))
    if "sdfstudio" in layouts:
        paths["sdfstudio"] = out_dir / "sdfstudio"
        write_sdfstudio(
            paths["sdfstudio"], views, K, width, height, SCENE_BOX, near, far, dataset_to_mesh, foreground_masks=not dtu_like
        )
    for layout, root in paths.items():
        if dtu_like and root is not None:
            write_object_masks(root, object_masks, layout)

    scene = {
        "format": "sp-plugins synthetic scene",
        "version": 1,
        "kind": "dtu-like" if dtu_like else "object on white",
        "source": str(mesh) if not hasattr(mesh, "faces") else "trimesh.Trimesh",
        "gt_mesh": GT_MESH_FILE,
        "normalization": {
            "formula": "x_dataset = (R_up @ x_mesh - center) * scale",
            "up_axis": up_axis,
            "R_up": up_rotation(up_axis)[:3, :3].tolist(),
            "center": center.tolist(),
            "scale": scale,
            "radius": radius,
        },
        "dataset_to_mesh": dataset_to_mesh.tolist(),
        "scene_box": {"aabb": [list(corner) for corner in SCENE_BOX]},
        "cameras": {
            "convention": "c2w OpenGL (camera looks down -Z, +Y up) in transforms_*.json; "
            "OpenCV (+Z forward, +Y down) in sdfstudio camtoworld; world +Z up; pixel centres at +0.5",
            "distance": camera_distance,
            "fov_x": fov,
            "width": width,
            "height": height,
            "near": near,
            "far": far,
            "seed": seed,
            "hemisphere": hemisphere,
            "supersample": supersample,
        },
        "splits": {split: len(dirs) for split, dirs in directions.items()},
        **({"dtu_like": _dtu_like_record(normalised, cap)} if dtu_like else {}),
        "layouts": {name: name for name in layouts},
        "nerfstudio": {
            "blender": "blender-data: x_nerfstudio = scale_factor * x_dataset (scale_factor defaults to 1.0); "
            "its scene box is fixed at [-1.5, 1.5]^3 (times nothing: it ignores scale_factor)",
            "sdfstudio": "sdfstudio-data: auto_orient rotates the mean camera up vector onto +Z; the training "
            "cameras here make that rotation the identity, so x_nerfstudio = x_dataset; scene box from meta_data.json",
        },
    }
    scene_json = out_dir / SCENE_FILE
    scene_json.write_text(json.dumps(scene, indent=2))
    return ScenePaths(out_dir, scene_json, gt_mesh, paths["blender"], paths["sdfstudio"])


def _dtu_like_record(normalised, cap: CapCameras) -> dict:
    _, ground_z = surroundings(normalised)
    return {
        "ground_z": ground_z,
        "ground_half_size": GROUND_HALF_SIZE,
        "backdrop_radius": BACKDROP_RADIUS,
        "cap": {"azimuth_span_deg": cap.azimuth_span, "elevation_deg": list(cap.elevation), "front": "-Y"},
        "object_masks": "object_mask/ in each layout: blender object_mask/<split>/r_<i>.png, sdfstudio "
        "object_mask/<split>_<i>.png; 255 where a pixel's first hit is the object (coverage >= 0.5)",
        "training_masks": "none: images are opaque (ground and backdrop behind the object)",
    }


def make_tiny_scene(out_dir: Union[str, Path], mesh: MeshSource = "torus", **overrides) -> ScenePaths:
    """A scene for tests: 8 training views (+2 val, +2 test) of 32x32, one ray per pixel; well under a second."""
    settings = dict(n_train=8, n_val=2, n_test=2, resolution=32, supersample=1, seed=0)
    settings.update(overrides)
    return make_scene(mesh, out_dir, **settings)
