import json

import pytest

from sp_plugins.cli import demo


def test_demo_writes_a_results_table_meshes_renders_and_a_plot(tmp_path, capsys):
    out = tmp_path / "demo"
    assert demo.main(["--budget", "quick", "--steps", "12", "--out", str(out), "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    assert "| metric | baseline | SP | SP / baseline |" in printed
    results = json.loads((out / "results.json").read_text())
    assert results["steps"] == 12
    for name in ("baseline", "SP"):
        m = results["metrics"][name]
        assert m["chamfer"] > 0 and 0 <= m["fscore"] <= 1
        assert len(results["curves"][name]["loss"]) == 12
    assert (out / "meshes" / "baseline.ply").stat().st_size > 0
    assert (out / "meshes" / "sp.ply").stat().st_size > 0
    for png in ("renders.png", "slices.png", "convergence.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "scene" / "blender" / "transforms_train.json").is_file()


def test_demo_refuses_to_overwrite_earlier_results(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "results.json").write_text("{}")
    assert demo.main(["--steps", "12", "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "results.json").read_text() == "{}"


@pytest.mark.parametrize("args, word", [
    (["--steps", "3"], "--steps"),
    (["--mesh", "/nonexistent.ply"], "--mesh /nonexistent.ply: mesh '/nonexistent.ply' is neither an existing file"),
    (["--mesh", "EMPTY"], "has no triangle faces"),
    (["--threads", "0"], "--threads must be at least 1"),
])
def test_demo_bad_input_is_one_clear_line(tmp_path, capsys, args, word):
    if "EMPTY" in args:
        empty = tmp_path / "empty.ply"
        empty.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n")
        args = [str(empty) if a == "EMPTY" else a for a in args]
    assert demo.main([*args, "--out", str(tmp_path / "d")]) == 2
    captured = capsys.readouterr()
    assert word in captured.err and captured.err.count("\n") == 1 and "Traceback" not in captured.err
    assert not (tmp_path / "d").exists()  # refused before creating --out

