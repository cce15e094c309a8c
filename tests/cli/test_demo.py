import json

import pytest

from sp_plugins.cli import demo


def test_demo_writes_a_results_table_meshes_renders_and_a_plot(tmp_path, capsys):
    out = tmp_path / "demo"
    # the final meshes at 48^3, not the budget's 128^3 (their grid queries were 3/4 of this test's time)
    assert demo.main(["--budget", "quick", "--steps", "12", "--mesh-resolution", "48", "--out", str(out), "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    assert "| metric | baseline | SP | SP / baseline |" in printed
    results = json.loads((out / "results.json").read_text())
    assert results["steps"] == 12
    for name in ("baseline", "SP"):
        m = results["metrics"][name]
        assert m["chamfer"] > 0 and 0 <= m["fscore"] <= 1
        assert len(results["curves"][name]["loss"]) == 12
    # the two runs share seed, init and batches (same config but for sp), so their losses differ
    # only through SP: from the first step (SP perturbs step 0 on), not only later; a demo whose SP
    # run is a second baseline has two identical curves
    base_loss, sp_loss = results["curves"]["baseline"]["loss"], results["curves"]["SP"]["loss"]
    assert results["sp"]["alpha0"] > 0 and results["sp"]["end"] > 0
    assert sp_loss[0] != base_loss[0], "the SP run's first loss equals the baseline's: SP did not act"
    assert sum(a != b for a, b in zip(base_loss, sp_loss)) >= 10
    assert (out / "meshes" / "baseline.ply").stat().st_size > 0
    assert (out / "meshes" / "sp.ply").stat().st_size > 0
    for png in ("renders.png", "slices.png", "convergence.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "scene" / "blender" / "transforms_train.json").is_file()


def test_the_demos_two_runs_differ_only_in_sp():
    """What the demo compares: the SP run is the baseline's config with SP switched on (alpha > 0,
    ending inside training), nothing else changed, so any difference in results is SP's."""
    from dataclasses import replace

    args = demo.parse_args(["--budget", "quick"])
    configs = demo._paired_configs(args)
    base, sp = configs["baseline"], configs["SP"]
    assert not base.sp.enabled or base.sp.alpha0 == 0
    assert sp.sp.enabled and sp.sp.alpha0 == args.alpha0 > 0 and 0 < sp.sp.end < 1
    assert base.mesh_resolution == demo.BUDGETS["quick"][2]  # the budget's grid unless --mesh-resolution
    assert demo._paired_configs(demo.parse_args(["--mesh-resolution", "64"]))["SP"].mesh_resolution == 64
    assert replace(sp, sp=base.sp) == base
    steps = base.steps
    alphas = [sp.sp.setup(total_steps=steps, bounds=(-1.0, 1.0), dim=3).set_step(i, steps) for i in (0, steps - 1)]
    assert alphas[0] > 0 and alphas[1] == 0  # on from step 0, off by the last step


def test_demo_refuses_to_overwrite_earlier_results(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "results.json").write_text("{}")
    assert demo.main(["--steps", "12", "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "results.json").read_text() == "{}"


@pytest.mark.parametrize("args, word", [
    (["--steps", "3"], "--steps"),
    (["--mesh-resolution", "8"], "--mesh-resolution 8: use at least 16"),
    (["--mesh-resolution", "0"], "--mesh-resolution 0: use at least 16"),
    (["--steps", "0"], "--steps 0: use at least 10"),
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

