"""bench.harness.scenes: a rendered scene is reused only for the mesh it was rendered from (the bundled
``spot`` and ../shared's spot.ply are the same name and different scenes), and ``SP_SHARED_DATA``
moves the shared data."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the checkout: bench/ is not an installed package
from bench.harness import scenes  # noqa: E402

TINY = dict(views=2, test_views=1, resolution=(8, 6))


def test_a_cached_scene_of_another_mesh_is_refused_in_one_line(tmp_path):
    root = scenes.rendered("sphere", tmp_path, **TINY)
    assert json.loads((root / "scene.json").read_text())["source"] == "sphere"
    assert scenes.rendered("sphere", tmp_path, **TINY) == root  # the same mesh: reused
    info = json.loads((root / "scene.json").read_text())
    info["source"] = "/elsewhere/sphere.ply"  # what a run with ../shared would have rendered it from
    (root / "scene.json").write_text(json.dumps(info))
    with pytest.raises(SystemExit, match=r"rendered from /elsewhere/sphere.ply, not sphere .*remove that folder"):
        scenes.rendered("sphere", tmp_path, **TINY)


def test_shared_data_moves_with_sp_shared_data(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "spot.ply").write_bytes(b"ply")
    code = "from bench.harness import scenes; print(scenes.mesh_source('spot')); print(scenes.FOX)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True,
                         env={"SP_SHARED_DATA": str(tmp_path), "PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)}).stdout.split()
    assert out == [str(tmp_path / "meshes" / "spot.ply"), str(tmp_path / "real" / "fox")]
