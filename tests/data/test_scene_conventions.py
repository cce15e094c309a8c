"""Camera conventions of the written datasets, read back from disk (not from the renderer's memory).

Every vertex of the true mesh, occluded or not, projects inside the object's silhouette, so the
fraction of vertices that land in each frame's mask measures whether a layout's camera matrices,
intrinsics and axis conventions agree with its images. Spot is used because it has no symmetry
that would hide a flipped axis (a torus would).
"""

import json

import imageio.v2 as imageio
import numpy as np
import pytest
import trimesh
from scipy.ndimage import binary_dilation

from sp_plugins.data import make_tiny_scene

SPLITS = ("train", "val", "test")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    # 4x4 rays per pixel: a vertex on a thin horn still marks its pixel in the alpha mask.
    return make_tiny_scene(tmp_path_factory.mktemp("spot"), mesh="spot", supersample=4, seed=3)


def _fraction_in_mask(pixels_uv: np.ndarray, mask: np.ndarray) -> float:
    """Fraction of (u, v) image points inside `mask`, allowing one pixel for silhouette discretisation."""
    mask = binary_dilation(mask)
    height, width = mask.shape
    cols, rows = np.floor(pixels_uv[:, 0]).astype(int), np.floor(pixels_uv[:, 1]).astype(int)
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    hits = np.zeros(len(pixels_uv), dtype=bool)
    hits[inside] = mask[rows[inside], cols[inside]]
    return float(hits.mean())


def _project_opengl(vertices, c2w, focal, cx, cy, check_front=True):
    cam = (vertices - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera (rotation is orthonormal)
    depth = -cam[:, 2]
    assert not check_front or (depth > 0).all(), "the mesh must be in front of every camera"
    return np.stack([focal * cam[:, 0] / depth + cx, -focal * cam[:, 1] / depth + cy], axis=-1)


def _project_opencv(vertices, c2w, K, check_front=True):
    cam = (vertices - c2w[:3, 3]) @ c2w[:3, :3]
    assert not check_front or (cam[:, 2] > 0).all(), "the mesh must be in front of every camera"
    return np.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], axis=-1)


def _k(focal, width, height):
    return np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])


def _blender_frames(root, split):
    meta = json.loads((root / f"transforms_{split}.json").read_text())
    for frame in meta["frames"]:
        image = imageio.imread(root / (frame["file_path"].replace("./", "") + ".png"))
        assert image.shape[-1] == 4, "Blender images are RGBA"
        width = image.shape[1]
        focal = 0.5 * width / np.tan(0.5 * meta["camera_angle_x"])
        yield np.asarray(frame["transform_matrix"]), focal, image


def _sdfstudio_frames(root, split):
    name = "meta_data.json" if split == "train" else f"meta_data_{split}.json"
    meta = json.loads((root / name).read_text())
    for frame in meta["frames"]:
        image = imageio.imread(root / frame["rgb_path"])
        mask = imageio.imread(root / frame["foreground_mask"]) > 127
        assert image.shape == (meta["height"], meta["width"], 3), "SDFStudio images are RGB of the stated size"
        yield np.asarray(frame["camtoworld"]), np.asarray(frame["intrinsics"])[:3, :3], image, mask


def test_blender_cameras_project_mesh_into_alpha_mask(scene):
    vertices = trimesh.load(scene.gt_mesh, process=False).vertices
    right, flipped = [], []
    for split in SPLITS:
        for c2w, focal, image in _blender_frames(scene.blender, split):
            height, width = image.shape[:2]
            mask = image[..., 3] > 0
            right.append(_fraction_in_mask(_project_opengl(vertices, c2w, focal, width / 2, height / 2), mask))
            # The same matrix read as an OpenCV camera (a classic bug) must fail the check.
            flipped.append(_fraction_in_mask(_project_opencv(vertices, c2w, _k(focal, width, height), check_front=False), mask))
    assert len(right) == 12
    assert min(right) >= 0.99, right
    assert np.mean(flipped) < 0.85, flipped


def test_sdfstudio_cameras_project_mesh_into_mask(scene):
    vertices = trimesh.load(scene.gt_mesh, process=False).vertices
    right, unflipped = [], []
    for split in SPLITS:
        for c2w, K, image, mask in _sdfstudio_frames(scene.sdfstudio, split):
            right.append(_fraction_in_mask(_project_opencv(vertices, c2w, K), mask))
            # Reading the OpenCV matrix as OpenGL (forgetting the flip) must fail the check.
            unflipped.append(_fraction_in_mask(_project_opengl(vertices, c2w, K[0, 0], K[0, 2], K[1, 2], check_front=False), mask))
            background = ~binary_dilation(mask)
            assert (image[background] == 255).all(), "the SDFStudio background is white"
    assert len(right) == 12
    assert min(right) >= 0.99, right
    assert np.mean(unflipped) < 0.85, unflipped


def test_layouts_share_cameras_and_images(scene):
    """Both layouts describe the same views: equal poses after the OpenGL/OpenCV flip, equal pixels."""
    for split in SPLITS:
        blender = list(_blender_frames(scene.blender, split))
        sdfstudio = list(_sdfstudio_frames(scene.sdfstudio, split))
        assert len(blender) == len(sdfstudio)
        for (c2w_gl, focal, rgba), (c2w_cv, K, rgb, mask) in zip(blender, sdfstudio):
            np.testing.assert_allclose(c2w_gl @ np.diag([1, -1, -1, 1]), c2w_cv, atol=1e-12)
            np.testing.assert_allclose(K[0, 0], focal, rtol=1e-9)
            alpha = rgba[..., 3:] / 255.0
            composite = rgba[..., :3] * alpha + 255.0 * (1.0 - alpha)
            assert np.abs(composite - rgb).max() <= 1.5  # two 8-bit roundings
            np.testing.assert_array_equal(mask, rgba[..., 3] >= 128)


def test_training_cameras_are_balanced_and_look_at_origin(scene):
    """Training cameras: mean up vector exactly +Z (nerfstudio's auto-orient is then the identity)."""
    poses = np.stack([frame[0] for frame in _blender_frames(scene.blender, "train")])
    up = poses[:, :3, 1].mean(axis=0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
    forward = -poses[:, :3, 2]
    to_origin = -poses[:, :3, 3] / np.linalg.norm(poses[:, :3, 3], axis=1, keepdims=True)
    np.testing.assert_allclose(forward, to_origin, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3], axis=1), 4.0)
    rotations = poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0)
