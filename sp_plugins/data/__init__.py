"""Synthetic multi-view scenes rendered from a mesh, in nerfstudio's Blender and SDFStudio layouts.

    from sp_plugins.data import make_scene, make_tiny_scene, load_gt_mesh, dataset_to_nerfstudio
"""

from sp_plugins.data.cameras import look_at_origin, opengl_to_opencv
from sp_plugins.data.coords import dataset_to_nerfstudio, load_gt_mesh, read_scene, scene_root
from sp_plugins.data.mesh import PRIMITIVES, load_mesh, normalize_mesh
from sp_plugins.data.render import render_views
from sp_plugins.data.scene import LAYOUTS, SCENE_BOX, SceneExistsError, ScenePaths, make_scene, make_tiny_scene

__all__ = [
    "LAYOUTS",
    "PRIMITIVES",
    "SCENE_BOX",
    "SceneExistsError",
    "ScenePaths",
    "dataset_to_nerfstudio",
    "load_gt_mesh",
    "load_mesh",
    "look_at_origin",
    "make_scene",
    "make_tiny_scene",
    "normalize_mesh",
    "opengl_to_opencv",
    "read_scene",
    "render_views",
    "scene_root",
]
