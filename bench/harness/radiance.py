"""What the radiance-field studies share (``bench.radiance_methods``, ``bench.sparse_views``): their
output folder and scenes, the CPU-sized MipNeRF and its config, and the key that names a finished run."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Optional, Tuple

import torch

from bench.harness import scenes
from bench.harness.common import OUT_DIR

OUT = OUT_DIR / "radiance_methods"
"""Scenes and runs of both studies (``bench.sparse_views`` writes its results next to it)."""
SCENES = {"spot": "spot", "cow": scenes.mesh_source("cow"), "bunny": scenes.mesh_source("bunny")}
"""The studies' meshes. ``spot`` is the bundled mesh (Z-up) in the white-background scenes, and
../shared's spot.ply (Y-up) where present in the DTU-like ones (:func:`bench.harness.scenes.rendered`
resolves names through ``mesh_source``)."""
SCALE = 1.5
"""Blender-data scale factor: the [-1.5, 1.5]^3 box nerfstudio fixes for Blender scenes then holds the
object (radius 0.85 * 1.5) as [-1, 1]^3 holds it unscaled."""
BOX = torch.tensor([[-1.5] * 3, [1.5] * 3])
"""nerfstudio's fixed scene box for Blender data."""
DTU_UP_AXIS = {"spot": "z", "cow": "y", "bunny": "y"}
"""Up axis of each scene's mesh (the DTU-like scene stands it on its ground). ``spot``'s z is its
bundled file's up; ../shared's spot.ply (Y-up), which the issue-21 and issue-31 studies used, stands
on its haunches, nose up, under it: kept, so those results reproduce."""


@dataclasses.dataclass
class MipBudget:
    """CPU-sized MipNeRF: nerfstudio's 8x256 MLP with 128+128 samples x 1024 rays takes >1 s per
    step here even at a quarter of that, so the MLP is narrower and the batch smaller."""

    steps: int = 3000
    """training steps of every run"""
    rays: int = 256
    """rays per training batch"""
    coarse: int = 32
    """samples per ray of the coarse pass"""
    fine: int = 32
    """samples per ray of the fine pass"""
    mlp_num_layers: int = 4
    """layers of MipNeRF's MLP (nerfstudio: 8)"""
    mlp_layer_width: int = 128
    """width of MipNeRF's MLP (nerfstudio: 256)"""
    head_width: int = 64
    """width of the colour head"""
    lr: float = 5e-4
    """Adam learning rate of the fields"""
    views: int = 6
    """training views of the white-background scene"""
    alpha0: float = 0.04
    """the SP run's initial alpha (the preset of sp-mipnerf)"""
    end: int = 1000
    """the step at which the SP run's alpha reaches 0"""
    image: int = 64
    """side in pixels of the white-background scene's renders"""
    test_views: int = 8
    """held-out views scored (white-background scene)"""
    dtu_like: bool = False
    """train on the DTU-like scene (``sp-scene --dtu-like``: ground, backdrop, a frontal cap of 49
    views of 96x72, no masks; ``image`` and ``test_views`` do not apply) and score PSNR inside the
    object mask too, as RegNeRF / FreeNeRF do on DTU; the far plane then reaches the backdrop."""
    view_selection: str = "spread"
    """which of the training views to keep (sp_plugins.nerfstudio.components.views): spread / first / random"""


OMITTED_FROM_KEY = {"background": "white", "align_corners": True, "density_units": "voxel", "loss": "mse",
                    "diffuse_loss_weight": 0.0, "lr_schedule": "exponential", "decay_every": 3 / 28, "stage_gamma": 1.0,
                    "sp_first_decay": 12 / 28, "dtu_like": False, "view_selection": "spread"}
"""Settings added after the first tables: left out of the key at their defaults, so finished runs stay found."""


def budget_key(*parts) -> str:
    """Ten hex digits naming a finished run by its scene, budget and settings (dataclasses by their fields)."""

    def plain(p):
        if not dataclasses.is_dataclass(p):
            return p
        d = dataclasses.asdict(p)
        return {k: v for k, v in d.items() if OMITTED_FROM_KEY.get(k, object()) != v}

    text = json.dumps([plain(p) for p in parts], sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def scene_dir(scene: str, views: int, image: int, test_views: int) -> Path:
    """The white-background scene of ``scene`` (a key of :data:`SCENES` or a mesh file), rendered once."""
    path = OUT / "scenes" / f"{Path(scene).stem}-{views}v-{image}px"
    return scenes.synthetic(SCENES.get(scene, scene), path, views=views, test_views=test_views, resolution=image) / "blender"


def dtu_scene_dir(scene: str, up_axis: Optional[str] = None, **sizes) -> Path:
    """The DTU-like scene (``bench.harness.scenes.rendered``) at its full size (49 + 3 views of 96x72)
    unless ``sizes`` (views, test_views, resolution) say otherwise; rendered once. ``scene`` is a key
    of :data:`SCENES` or any mesh file (standing on its ``up_axis``, z unless known)."""
    up = up_axis or DTU_UP_AXIS.get(scene, "z")
    return scenes.rendered(SCENES.get(scene, scene), OUT, up_axis=up, **sizes) / "blender"


def dtu_near_far(data: Path) -> Tuple[float, float]:
    """Near and far planes that hold the whole DTU-like scene for every camera: from just inside the
    closest approach of the object's sphere to the far side of the backdrop sphere."""
    info = json.loads((data.parent / "scene.json").read_text())
    distance = info["cameras"]["distance"]
    near = max(0.05, distance - info["normalization"]["radius"] - 0.5)
    return near, distance + info["dtu_like"]["backdrop_radius"] + 0.5


def mip_config(sp: bool, data: Path, budget: MipBudget, seed: int, out: Path, method: str = "sp-mipnerf",
               name: Optional[str] = None):
    """``method`` (sp-mipnerf, or freenerf-lite: the same MipNeRF) at ``budget``, SP on or off."""
    from sp_plugins.adapter.shrink import shrink
    from sp_plugins.nerfstudio.runs import configure_run, method_config

    config = method_config(method)
    m = config.pipeline.model
    shrink(config, num_coarse_samples=budget.coarse, num_importance_samples=budget.fine, mlp_num_layers=budget.mlp_num_layers,
           mlp_layer_width=budget.mlp_layer_width, head_mlp_layer_width=budget.head_width, eval_num_rays_per_chunk=4096,
           sp=dataclasses.replace(m.sp, enabled=sp, alpha0=budget.alpha0, end=budget.end, seed=seed), lr={"fields": budget.lr})
    if budget.dtu_like:
        near, far = dtu_near_far(data)
        m.collider_params = {"near_plane": near, "far_plane": far}
    name = name or ("sp-mipnerf" if sp else "mipnerf")
    configure_run(config, data, steps=budget.steps, output_dir=out, layout="blender", rays_per_batch=budget.rays,
                  experiment_name=name)
    config.pipeline.datamanager.train_views = budget.views
    config.pipeline.datamanager.train_view_selection = budget.view_selection
    return config
