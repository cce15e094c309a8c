"""sp-scene: writes a scene, and fails with one clear line (no traceback) on bad input."""

import json
import subprocess
import sys

import trimesh

from sp_plugins.cli.scene import main


def test_cli_writes_requested_scene(tmp_path, capsys):
    out = tmp_path / "scene"
    code = main(["torus", str(out), "--views", "6", "--val-views", "1", "--test-views", "3", "--resolution", "40x24",
                 "--layouts", "sdfstudio", "--seed", "2", "--supersample", "1", "--quiet"])
    assert code == 0
    meta = json.loads((out / "sdfstudio" / "meta_data.json").read_text())
    assert (meta["width"], meta["height"], len(meta["frames"])) == (40, 24, 6)
    assert len(json.loads((out / "sdfstudio" / "meta_data_test.json").read_text())["frames"]) == 3
    assert not (out / "blender").exists()
    assert len(trimesh.load(out / "gt_mesh.ply").faces) > 0
    assert capsys.readouterr().out == ""


def test_cli_refuses_existing_scene_then_overwrites(tmp_path, capsys):
    args = ["sphere", str(tmp_path), "--views", "4", "--val-views", "1", "--test-views", "1", "--resolution", "16", "--quiet"]
    assert main(args) == 0
    assert main(args) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(args + ["--overwrite"]) == 0


def test_cli_reports_unreadable_mesh_without_traceback(tmp_path):
    broken = tmp_path / "broken.obj"
    broken.write_text("this is not a mesh\n")
    result = subprocess.run(
        [sys.executable, "-m", "sp_plugins.cli.scene", str(broken), str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2
    assert "sp-scene: error:" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()
