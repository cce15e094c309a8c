"""DTU-like scenes (`sp-scene --dtu-like`): cameras on a frontal cap, opaque images with ground and
backdrop behind the object, object masks and the true mesh consistent with the images (read back
from disk, both layouts)."""

import json
import shutil
import subprocess
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import trimesh
from scipy.ndimage import binary_dilation

from sp_plugins.cli.scene import main
from sp_plugins.data import make_scene
from sp_plugins.data.dtu_like import CapCameras, backdrop_albedo, ground_albedo

SPLITS = ("train", "val", "test")
CAP = CapCameras(azimuth_span=80.0, elevation=(15.0, 45.0))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene("spot", tmp_path_factory.mktemp("dtu"), dtu_like=True, cap=CAP, n_train=12, n_val=2, n_test=3,
                      resolution=(48, 36), supersample=2, seed=4)


def _blender(scene, split):
    meta = json.loads((scene.blender / f"transforms_{split}.json").read_text())
    for index, frame in enumerate(meta["frames"]):
        image = imageio.imread(scene.blender / (frame["file_path"].replace("./", "") + ".png"))
        mask = imageio.imread(scene.blender / "object_mask" / split / f"r_{index}.png") > 127
        focal = 0.5 * image.shape[1] / np.tan(0.5 * meta["camera_angle_x"])
        yield np.asarray(frame["transform_matrix"]), focal, image, mask


def _project(vertices, c2w, focal, width, height):
    cam = (vertices - c2w[:3, 3]) @ c2w[:3, :3]  # OpenGL camera frame
    depth = -cam[:, 2]
    assert (depth > 0).all()
    return np.stack([focal * cam[:, 0] / depth + width / 2, -focal * cam[:, 1] / depth + height / 2], axis=-1)


def test_cameras_sit_on_the_frontal_cap(scene):
    info = json.loads(scene.scene_json.read_text())
    assert info["kind"] == "dtu-like" and info["splits"] == {"train": 12, "val": 2, "test": 3}
    for split in SPLITS:
        for c2w, *_ in _blender(scene, split):
            position = c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
            elevation = np.degrees(np.arcsin(position[2]))
            azimuth = np.degrees(np.arctan2(position[1], position[0]))  # the cap's centre is -Y: -90 degrees
            assert 15.0 - 1e-6 <= elevation <= 45.0 + 1e-6, elevation
            assert abs(azimuth + 90.0) <= 40.0 + 1e-6, azimuth
            np.testing.assert_allclose(-c2w[:3, 2], -position, atol=1e-9)  # looking at the origin
    # the training grid spreads over the cap: both ends of each range are approached
    train = np.stack([c2w[:3, 3] for c2w, *_ in _blender(scene, "train")])
    azimuths = np.degrees(np.arctan2(train[:, 1], train[:, 0])) + 90.0
    assert azimuths.min() < -20.0 and azimuths.max() > 20.0, azimuths


def test_images_are_opaque_and_show_ground_and_backdrop(scene):
    info = json.loads(scene.scene_json.read_text())["dtu_like"]
    backdrops = 0
    for c2w, focal, image, mask in _blender(scene, "train"):
        assert (image[..., 3] == 255).all(), "DTU-like images have no transparent background"
        rgb = image[..., :3].astype(float)
        outside = ~binary_dilation(mask, iterations=1)
        assert outside.mean() > 0.3
        assert (rgb[outside] >= 250).all(axis=-1).mean() < 0.01, "the background is not white"
        # the bottom centre pixel looks down at the ground: a warm ground colour (R > G > B, as every
        # ground texel), no brighter than the brightest ground texel
        height, width = mask.shape
        direction = np.array([0.0, -(height - 0.5 - height / 2) / focal, -1.0]) @ c2w[:3, :3].T
        assert direction[2] < 0 and (info["ground_z"] - c2w[2, 3]) / direction[2] > 0
        if not binary_dilation(mask)[-1, width // 2]:
            red, green, blue = rgb[-1, width // 2]
            assert red > green > blue, rgb[-1, width // 2]
            assert red <= 255 * ground_albedo(np.array([[0.1, 0.1, 0.0]]))[0].max() / 0.75 + 2
        backdrops += int(c2w[2, 3] / np.linalg.norm(c2w[:3, 3]) < np.sin(np.radians(30)))
    assert backdrops > 0
    # sdfstudio layout: the same opaque views, and no training masks
    meta = json.loads((scene.sdfstudio / "meta_data.json").read_text())
    assert meta["has_foreground_mask"] is False
    assert all("foreground_mask" not in frame for frame in meta["frames"])
    assert not (scene.sdfstudio / "mask").exists()
    for index, (frame, (_, _, rgba, _)) in enumerate(zip(meta["frames"], _blender(scene, "train"))):
        rgb = imageio.imread(scene.sdfstudio / frame["rgb_path"])
        np.testing.assert_array_equal(rgb, rgba[..., :3])
        sdf_mask = imageio.imread(scene.sdfstudio / "object_mask" / f"train_{index:03d}.png")
        blender_mask = imageio.imread(scene.blender / "object_mask" / "train" / f"r_{index}.png")
        np.testing.assert_array_equal(sdf_mask, blender_mask)


def test_backdrop_is_visible_behind_the_object(scene):
    """The lowest camera's top row passes over the ground's edge onto the backdrop sphere: those pixels
    carry the backdrop's (unshaded, smooth) texture at the geometric hit point."""
    info = json.loads(scene.scene_json.read_text())["dtu_like"]
    c2w, focal, image, mask = min(_blender(scene, "train"), key=lambda view: view[0][2, 3])
    height, width = mask.shape
    origin = c2w[:3, 3]
    checked = 0
    for j in range(width):
        if binary_dilation(mask)[0, j]:
            continue
        d = np.array([(j + 0.5 - width / 2) / focal, (height / 2 - 0.5) / focal, -1.0]) @ c2w[:3, :3].T
        d /= np.linalg.norm(d)
        b = origin @ d
        t_sphere = -b + np.sqrt(b * b - origin @ origin + info["backdrop_radius"] ** 2)
        t_ground = (info["ground_z"] - origin[2]) / d[2] if d[2] < 0 else np.inf
        on_ground = np.all(np.abs((origin + t_ground * d)[:2]) <= info["ground_half_size"]) if np.isfinite(t_ground) else False
        if on_ground and t_ground < t_sphere:
            continue
        expected = 255 * backdrop_albedo((origin + t_sphere * d)[None])[0]
        np.testing.assert_allclose(image[0, j, :3], expected, atol=3)
        checked += 1
    assert checked >= width // 2, checked


def test_masks_and_true_mesh_agree_with_images(scene):
    """Every vertex of the true object projects into its view's object mask, and every mask pixel is near one."""
    mesh = trimesh.load(scene.gt_mesh, process=False)
    vertices = mesh.vertices
    dense = mesh.sample(20000, seed=0) if hasattr(mesh, "sample") else vertices
    fractions, covered = [], []
    for split in SPLITS:
        for c2w, focal, image, mask in _blender(scene, split):
            height, width = mask.shape
            uv = _project(vertices, c2w, focal, width, height)
            cols, rows = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
            fractions.append(binary_dilation(mask)[rows[inside], cols[inside]].mean())
            uv = _project(dense, c2w, focal, width, height)
            hit = np.zeros_like(mask)
            cols, rows = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
            hit[rows[inside], cols[inside]] = True
            covered.append(binary_dilation(hit)[mask].mean())
    assert min(fractions) >= 0.99, fractions
    assert min(covered) >= 0.98, covered
    # the mask is where the object is in front: outside it, the pixel colour is not the object's
    assert 0.05 < np.mean([m.mean() for *_, m in _blender(scene, "train")]) < 0.6


def test_cli_dtu_like_and_its_refusals(tmp_path, capsys):
    sp_scene = shutil.which("sp-scene") or str(Path(__import__("sys").executable).parent / "sp-scene")
    out = tmp_path / "scene"
    run = subprocess.run([sp_scene, "box", str(out), "--dtu-like", "--views", "5", "--val-views", "1", "--test-views", "1",
                          "--resolution", "24x16", "--supersample", "1", "--cap-elevation", "20", "40", "--quiet"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    info = json.loads((out / "scene.json").read_text())
    assert info["dtu_like"]["cap"]["elevation_deg"] == [20.0, 40.0]
    assert len(list((out / "blender" / "object_mask" / "train").glob("*.png"))) == 5
    for bad, words in ((["--cap-azimuth", "90"], "--dtu-like"), (["--dtu-like", "--hemisphere"], "hemisphere"),
                       (["--dtu-like", "--cap-elevation", "50", "10"], "elevation")):
        with pytest.raises(SystemExit) as stop:  # in-process: argparse's one-line usage error
            code = main(["box", str(tmp_path / "bad"), "--views", "2", "--resolution", "8", "--quiet", *bad])
            raise SystemExit(code)
        err = capsys.readouterr().err
        assert stop.value.code == 2, (bad, err)
        assert words in err and "Traceback" not in err, err
        assert not (tmp_path / "bad").exists()
