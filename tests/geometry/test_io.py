import numpy as np
import pytest
import trimesh
from trimesh.exchange.ply import export_ply

from sp_plugins.geometry import Frame, load_mesh, load_oriented_points, save_mesh


def write_cloud(path, points, normals=None):
    cloud = trimesh.Trimesh(vertices=points, faces=np.zeros((0, 3), dtype=np.int64), vertex_normals=normals, process=False)
    path.write_bytes(export_ply(cloud, vertex_normal=normals is not None))
    return path


def sphere_points(n=2000, seed=0):
    p = np.random.default_rng(seed).standard_normal((n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def test_mesh_round_trip_and_sampling(tmp_path):
    mesh = trimesh.creation.icosphere(3)
    path = save_mesh(mesh, tmp_path / "sub" / "m.ply")
    back = load_mesh(path)
    assert len(back.faces) == len(mesh.faces)
    pts = load_oriented_points(path, n_points=500)
    assert pts.source == "mesh" and pts.points.shape == (500, 3) and pts.mesh is not None
    # icosphere face normals point outward
    assert (np.sum(pts.normals * pts.points, axis=1) > 0.9).all()


def test_cloud_normals_are_read_refused_or_estimated(tmp_path):
    p = sphere_points()
    with_n = load_oriented_points(write_cloud(tmp_path / "n.ply", p, p))
    assert with_n.source == "file"
    np.testing.assert_allclose(with_n.normals, p, atol=1e-5)
    bare = write_cloud(tmp_path / "bare.ply", p)
    with pytest.raises(ValueError, match="no normals"):
        load_oriented_points(bare)
    est = load_oriented_points(bare, estimate_missing_normals=True)
    assert est.source == "estimated"
    assert np.mean(np.sum(est.normals * p, axis=1) > 0.95) > 0.98


def test_bad_files_give_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load_mesh(tmp_path / "missing.ply")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"this is not a ply file")
    with pytest.raises(ValueError, match="cannot be read"):
        load_mesh(junk)
    with pytest.raises(ValueError, match="no faces"):
        load_mesh(write_cloud(tmp_path / "c.ply", sphere_points(), sphere_points()))
    mesh = trimesh.creation.box()
    mesh.vertices[0] = np.nan
    nan_path = tmp_path / "nan.ply"
    nan_path.write_bytes(export_ply(mesh))
    with pytest.raises(ValueError, match="NaN"):
        load_mesh(nan_path)
    p = sphere_points()
    p[3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        load_oriented_points(write_cloud(tmp_path / "nanc.ply", p, sphere_points()))


def test_frame_fits_the_box_and_inverts():
    pts = np.random.default_rng(1).uniform([-3, 10, 0], [7, 12, 1], (1000, 3))
    frame = Frame.fit(pts, diagonal=1.9)
    local = frame.to_frame(pts)
    lo, hi = local.min(0), local.max(0)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.9)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
    np.testing.assert_allclose(frame.from_frame(local), pts, atol=1e-9)
