"""make_scene: mesh sources, normalisation, determinism, shading, and refusal to overwrite."""

import json
import sys

import imageio.v2 as imageio
import numpy as np
import pytest
import trimesh

from sp_plugins.data import (
    PRIMITIVES,
    SceneExistsError,
    load_mesh,
    make_scene,
    make_tiny_scene,
    read_scene,
)
from sp_plugins.data.render import LIGHT_DIRECTION, shade


def test_normalisation_is_recorded_and_invertible(tmp_path):
    source = trimesh.creation.box(extents=(4.0, 2.0, 1.0))
    source.apply_translation([10.0, -3.0, 2.0])
    paths = make_tiny_scene(tmp_path, mesh=source, up_axis="y")
    scene = read_scene(paths.blender)  # a layout directory finds its scene too
    gt = trimesh.load(paths.gt_mesh, process=False)
    assert np.linalg.norm(gt.vertices, axis=1).max() == pytest.approx(0.85)
    np.testing.assert_allclose(gt.bounds.mean(axis=0), 0.0, atol=1e-9)
    to_mesh = np.asarray(scene["dataset_to_mesh"])
    back = trimesh.transform_points(gt.vertices, to_mesh)
    np.testing.assert_allclose(np.sort(back, axis=0), np.sort(source.vertices, axis=0), atol=1e-9)
    # 'y' up: the source's tall axis (y, extent 2) becomes z.
    np.testing.assert_allclose(np.ptp(gt.vertices, axis=0) / np.ptp(gt.vertices, axis=0)[0], [1.0, 0.25, 0.5])
    meta = json.loads((paths.sdfstudio / "meta_data.json").read_text())
    np.testing.assert_allclose(meta["worldtogt"], to_mesh)
    assert scene["splits"] == {"train": 8, "val": 2, "test": 2}


@pytest.mark.parametrize("name", sorted(PRIMITIVES) + ["spot"])
def test_named_meshes_render_with_a_silhouette(tmp_path, name):
    paths = make_tiny_scene(tmp_path, mesh=name, layouts=("blender",))
    alpha = imageio.imread(paths.blender / "train" / "r_0.png")[..., 3]
    coverage = (alpha > 0).mean()
    assert 0.05 < coverage < 0.9, "the object is framed: visible, not clipped to the whole image"
    assert alpha[0].max() == alpha[-1].max() == alpha[:, 0].max() == alpha[:, -1].max() == 0, "border is background"
    assert paths.sdfstudio is None and not (tmp_path / "sdfstudio").exists()


def test_same_seed_same_scene_other_seed_other_cameras(tmp_path):
    first = make_tiny_scene(tmp_path / "a", seed=5)
    again = make_tiny_scene(tmp_path / "b", seed=5)
    other = make_tiny_scene(tmp_path / "c", seed=6)
    text = lambda paths: (paths.blender / "transforms_train.json").read_text()  # noqa: E731
    assert text(first) == text(again)
    np.testing.assert_array_equal(
        imageio.imread(first.sdfstudio / "rgb" / "val_001.png"), imageio.imread(again.sdfstudio / "rgb" / "val_001.png")
    )
    assert text(first) != text(other)


def test_held_out_cameras_differ_from_training_cameras(tmp_path):
    paths = make_tiny_scene(tmp_path, n_train=16, n_val=4, n_test=4)
    position = lambda split: np.array(  # noqa: E731
        [frame["transform_matrix"] for frame in json.loads((paths.blender / f"transforms_{split}.json").read_text())["frames"]]
    )[:, :3, 3]
    train = position("train")
    for split in ("val", "test"):
        nearest = np.linalg.norm(position(split)[:, None] - train[None], axis=-1).min(axis=1)
        assert (nearest > 1e-3).all()


def test_shading_depends_on_surface_not_view():
    """Radiance fields assume view-consistent colour: the same surface point from two sides of its
    normal's hemisphere has one colour."""
    mesh = load_mesh("sphere")
    triangles = np.arange(0, len(mesh.faces), 7)
    points = mesh.triangles_center[triangles]
    normals = mesh.face_normals[triangles]
    seen_head_on = shade(mesh, points, triangles, -normals)
    tangent = np.cross(normals, [0.3, 0.5, 0.8])
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    seen_grazing = shade(mesh, points, triangles, -normals + 0.9 * tangent)
    np.testing.assert_allclose(seen_head_on, seen_grazing)
    lit = normals @ LIGHT_DIRECTION > 0.5
    assert seen_head_on[lit].mean() > seen_head_on[~lit].mean() + 0.1, "facing the light is brighter"


def test_refuses_existing_scene_without_overwrite(tmp_path):
    make_tiny_scene(tmp_path)
    keep = tmp_path / "notes.txt"
    keep.write_text("mine")
    before = (tmp_path / "scene.json").read_text()
    with pytest.raises(SceneExistsError, match="overwrite"):
        make_tiny_scene(tmp_path, seed=9)
    assert (tmp_path / "scene.json").read_text() == before
    make_tiny_scene(tmp_path, seed=9, n_train=4, overwrite=True)
    assert keep.read_text() == "mine", "overwrite replaces only the scene's own files"
    assert read_scene(tmp_path)["cameras"]["seed"] == 9
    assert len(list((tmp_path / "blender" / "train").iterdir())) == 4, "stale images are gone"


def test_bad_inputs_raise_value_errors(tmp_path):
    garbage = tmp_path / "broken.ply"
    garbage.write_bytes(b"ply\nformat nonsense\n\x00\x01")
    with pytest.raises(ValueError, match="could not read|no triangle faces"):
        make_tiny_scene(tmp_path / "a", mesh=garbage)
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(50, 3))).export(cloud)
    with pytest.raises(ValueError, match="no triangle faces"):
        make_tiny_scene(tmp_path / "b", mesh=cloud)
    with pytest.raises(ValueError, match="neither an existing file nor a known name"):
        make_tiny_scene(tmp_path / "c", mesh="no_such_mesh.obj")
    with pytest.raises(ValueError, match="layouts"):
        make_tiny_scene(tmp_path / "d", layouts=("colmap",))
    with pytest.raises(ValueError, match="n_val"):
        make_scene("sphere", tmp_path / "e", n_val=0)
    with pytest.raises(ValueError, match="distance"):
        make_scene("sphere", tmp_path / "f", camera_distance=0.5)
    assert not any((tmp_path / name).exists() for name in "abcdef"), "nothing is written on bad input"


def test_ray_casters_agree_and_missing_embree_falls_back(monkeypatch):
    from sp_plugins.data.cameras import intrinsics, look_at_origin
    from sp_plugins.data.render import ray_intersector, render_views

    mesh = load_mesh("torus")
    c2w = look_at_origin(np.array([[1.5, -2.0, 1.0]]))
    K = intrinsics(16, 16, 1.0)
    fast = render_views(mesh, c2w, K, 16, 16, backend="embree")
    slow = render_views(mesh, c2w, K, 16, 16, backend="triangle")
    assert 0.1 < (fast[..., 3] > 0).mean() < 0.9
    np.testing.assert_array_equal(fast[..., 3], slow[..., 3])
    np.testing.assert_allclose(fast[..., :3], slow[..., :3], atol=1e-4)
    monkeypatch.setitem(sys.modules, "trimesh.ray.ray_pyembree", None)  # import now fails
    with pytest.warns(UserWarning, match="embreex"):
        assert type(ray_intersector(mesh)).__module__ == "trimesh.ray.ray_triangle"
    with pytest.raises(ValueError, match="pip install embreex"):
        ray_intersector(mesh, "embree")
