import json
import logging

import numpy as np
import pytest
import trimesh
from trimesh.exchange.ply import export_ply

from sp_plugins.cli.fit import main
from sp_plugins.tasks.image import save_image
from PIL import Image

TINY = ["--encoding.levels", "4", "--encoding.log2-table-size", "12", "--encoding.base-resolution", "8",
        "--encoding.max-resolution", "64", "--hidden", "16", "--quiet"]
TINY_SDF = TINY + ["--mesh-resolution", "32", "--refine", "2", "--metric-points", "3000"]


@pytest.fixture(scope="module")
def mesh_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("in") / "sphere.ply"
    path.write_bytes(export_ply(trimesh.creation.icosphere(2, radius=3.0)))
    return path


def read_json(path):
    return json.loads(path.read_text())  # strict: no NaN / Infinity


def read_png(path):
    with Image.open(path) as im:
        im.load()  # decodes the whole file: a truncated PNG fails here
        return im.size


def test_pointcloud_writes_mesh_metrics_and_curve(tmp_path, mesh_path):
    out = tmp_path / "run"
    args = ["pointcloud", str(mesh_path), "--out", str(out), "--steps", "12", "--seed", "3", "--n-points", "4000",
            "--surface-batch", "256", "--space-batch", "256", "--sp.alpha0", "0.03", "--sp.end", "0.5", "--geometric-init"] + TINY_SDF
    assert main(args) == 0
    metrics = read_json(out / "metrics.json")
    for key in ("chamfer", "normal_consistency", "fscore", "steps", "seconds", "sp"):
        assert key in metrics
    assert metrics["steps"] == 12 and metrics["sp"]["enabled"] is True and metrics["sp"]["alpha0"] == 0.03
    assert metrics["config"]["seed"] == 3 and metrics["normals"] == "mesh"
    assert min(read_png(out / "loss.png")) > 100
    mesh = trimesh.load(out / "mesh.ply")  # geometric init: a sphere from the start
    assert len(mesh.faces) > 0
    assert np.abs(mesh.vertices).max() > 1.2  # written back in the input's coordinates (radius 3), not the frame


def test_no_sp_and_overwrite(tmp_path, mesh_path, capsys):
    out = tmp_path / "run"
    base = ["pointcloud", str(mesh_path), "--out", str(out), "--steps", "3", "--n-points", "2000",
            "--surface-batch", "64", "--space-batch", "64"] + TINY_SDF
    assert main(base + ["--no-sp"]) == 0
    assert read_json(out / "metrics.json")["sp"]["enabled"] is False
    before = (out / "metrics.json").read_text()
    assert main(base) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "metrics.json").read_text() == before  # untouched
    assert main(base + ["--overwrite"]) == 0
    assert read_json(out / "metrics.json")["sp"]["enabled"] is True


def test_bad_inputs_give_clean_errors(tmp_path, mesh_path, capsys):
    empty = tmp_path / "cloud.ply"
    pts = np.random.default_rng(0).normal(size=(100, 3))
    empty.write_bytes(export_ply(trimesh.Trimesh(pts, np.zeros((0, 3), dtype=np.int64), process=False)))
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"garbage")
    nan_mesh = trimesh.creation.box()
    nan_mesh.vertices[0] = np.nan
    nan_path = tmp_path / "nan.ply"
    nan_path.write_bytes(export_ply(nan_mesh))
    nan_cloud = tmp_path / "nan_cloud.ply"
    pts_nan = pts.copy()
    pts_nan[5] = np.nan
    nan_cloud.write_bytes(export_ply(trimesh.Trimesh(pts_nan, np.zeros((0, 3), dtype=np.int64), process=False)))
    cases = [
        (["pointcloud", str(empty)], "no normals"),
        (["pointcloud", str(nan_cloud), "--estimate-normals"], "1 vertices have NaN or inf coordinates"),
        (["sdf", str(tmp_path / "missing.ply")], "no such file"),
        (["image", str(tmp_path / "missing.png")], "no such file"),
        (["sdf", str(tmp_path)], "is a folder; give a file inside it"),
        (["pointcloud", str(junk)], "cannot be read"),
        (["pointcloud", str(nan_path)], "NaN"),
        (["pointcloud", str(tmp_path / "missing.ply")], "no such file"),
        (["sdf", str(empty)], "no faces"),
        (["pointcloud", str(mesh_path), "--gt", str(empty)], "no faces"),  # a cloud cannot be the ground truth
        (["image", str(junk)], "cannot be read"),
    ]
    for args, message in cases:
        assert main(args + ["--out", str(tmp_path / "o"), "--quiet"]) == 2, args
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and err.count("\n") == 1
        assert not (tmp_path / "o").exists()  # a bad input leaves no empty --out behind
    a_file = tmp_path / "results.txt"
    a_file.write_text("mine")
    assert main(["sdf", str(mesh_path), "--out", str(a_file), "--quiet"]) == 2
    assert "exists and is not a folder; choose another --out" in capsys.readouterr().err
    assert a_file.read_text() == "mine"


@pytest.mark.parametrize("task", ["pointcloud", "image", "sdf"])
@pytest.mark.parametrize("flags, message", [
    (["--sp.alpha0", "-0.5"], "--sp.alpha0=-0.5: must be a finite number >= 0"),
    (["--sp.end", "500", "--steps", "20"], "--sp.end=500.0: the schedule ends at step 500, after the end of training (20 steps)"),
])
def test_bad_sp_flags_are_one_line_before_any_output(tmp_path, mesh_path, capsys, task, flags, message):
    out = tmp_path / "o"
    assert main([task, str(mesh_path), "--out", str(out), "--quiet", *flags]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"sp-fit: error: {message}" or (err.startswith(f"sp-fit: error: {message}") and err.count("\n") == 1)
    assert not out.exists()  # refused before creating --out or reading the input


def test_progress_bar_unless_quiet(tmp_path, mesh_path, capsys):
    base = ["pointcloud", str(mesh_path), "--steps", "4", "--n-points", "2000", "--surface-batch", "64",
            "--space-batch", "64"] + [a for a in TINY_SDF if a != "--quiet"]
    assert main(base + ["--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "sp-fit pointcloud" in err and "4/4" in err
    assert main(base + ["--out", str(tmp_path / "b"), "--quiet"]) == 0
    assert "4/4" not in capsys.readouterr().err


def test_point_cloud_without_normals_can_be_estimated(tmp_path, caplog):
    pts = np.random.default_rng(0).normal(size=(3000, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    cloud = tmp_path / "cloud.ply"
    cloud.write_bytes(export_ply(trimesh.Trimesh(pts, np.zeros((0, 3), dtype=np.int64), process=False)))
    gt = tmp_path / "gt.ply"
    gt.write_bytes(export_ply(trimesh.creation.icosphere(3)))
    out = tmp_path / "run"
    args = ["pointcloud", str(cloud), "--estimate-normals", "--gt", str(gt), "--out", str(out), "--steps", "3",
            "--surface-batch", "64", "--space-batch", "64"] + TINY_SDF
    with caplog.at_level(logging.WARNING):
        assert main(args) == 0
    assert "estimating them" in caplog.text  # the user is told the normals are not theirs
    metrics = read_json(out / "metrics.json")
    assert metrics["normals"] == "estimated" and metrics["gt"] == str(gt)


def test_image_with_alpha_map(tmp_path):
    img = np.random.default_rng(0).uniform(size=(48, 64, 3)).astype(np.float32)
    path = save_image(img, tmp_path / "in.png")
    out = tmp_path / "run"
    assert main(["image", str(path), "--out", str(out), "--steps", "5", "--adaptive-alpha"] + TINY) == 0
    metrics = read_json(out / "metrics.json")
    assert metrics["psnr"] > 0 and metrics["adaptive_alpha"] is True
    assert metrics["alpha_map_resolution"] == [4, 3]  # 64 x 48 pixels / 16
    assert read_png(out / "fitted.png") == (64, 48)
    for name in ("alpha_map.png", "loss.png"):
        assert min(read_png(out / name)) > 50
    # a rerun without the alpha map replaces the results and leaves no stale map behind
    assert main(["image", str(path), "--out", str(out), "--steps", "2", "--overwrite"] + TINY) == 0
    assert not (out / "alpha_map.png").exists() and read_json(out / "metrics.json")["adaptive_alpha"] is False


def test_sdf_command(tmp_path, mesh_path, capsys):
    out = tmp_path / "run"
    args = ["sdf", str(mesh_path), "--out", str(out), "--steps", "5", "--pool", "2000", "--batch", "256"] + TINY_SDF
    assert main(args) == 0
    metrics = read_json(out / "metrics.json")
    assert metrics["steps"] == 5 and "near_mae" in metrics and (out / "mesh.ply").exists()
    for key in ("chamfer", "normal_consistency", "fscore", "steps", "seconds", "sp"):
        assert key in metrics
    assert min(read_png(out / "loss.png")) > 100
    # an empty mesh (chamfer written as null) is never reported silently
    empty = metrics["chamfer"] is None
    assert ("the mesh is empty" in capsys.readouterr().err) == empty


def test_console_script_is_registered(capsys):
    from importlib.metadata import entry_points

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "sp-fit"]
    assert script.value == "sp_plugins.cli.fit:entrypoint"
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0 and "pointcloud" in capsys.readouterr().out


def test_quiet_fit_prints_no_stage_lines(tmp_path, mesh_path, capsys):
    out = tmp_path / "run"
    base = ["pointcloud", str(mesh_path), "--out", str(out), "--steps", "2", "--n-points", "2000",
            "--surface-batch", "64", "--space-batch", "64", "--device", "cpu"] + TINY_SDF
    assert main(base) == 0
    assert "meshing" not in capsys.readouterr().err
    assert read_json(out / "metrics.json")["device"] == "cpu"
