"""Sweep specs -> trials: the grid, the paired SP axis, seeds, sampling, stable keys, bad specs."""

from __future__ import annotations

import json
import subprocess

import pytest

from sp_plugins.sweeps import SpecError, expand, load_spec, spec_from_dict
from sp_plugins.sweeps.report import succeeded
from sp_plugins.sweeps.soundness import is_sound

FIT = {"command": "sp-fit pointcloud m.ply --steps 10", "grid": {"lr": ["1e-3", "1e-2"], "encoding.max-resolution": [32, 64]}}


def test_grid_times_sp_times_seeds_with_pairs_adjacent():
    trials = expand(spec_from_dict(dict(FIT, seeds=[0, 1])))
    assert len(trials) == 2 * 2 * 2 * 2
    assert len({t.key for t in trials}) == len(trials)
    for base, sp in zip(trials[::2], trials[1::2]):  # each SP trial follows its baseline
        assert (base.sp, sp.sp) == (False, True) and base.params == sp.params and base.seed == sp.seed
        assert "--no-sp" in base.argv and "--no-sp" not in sp.argv
    first = trials[0].argv
    assert first[:2] == ["sp-fit", "pointcloud"] and first[first.index("--lr") + 1] == "1e-3"
    assert first[first.index("--seed") + 1] == "0" and "--encoding.max-resolution" in first


def test_keys_are_stable_and_name_the_command():
    a, b = expand(spec_from_dict(FIT)), expand(spec_from_dict(FIT))
    assert [t.key for t in a] == [t.key for t in b]
    grown = expand(spec_from_dict(dict(FIT, grid=dict(FIT["grid"], lr=["1e-3", "1e-2", "3e-2"]))))
    assert {t.key for t in a} < {t.key for t in grown}  # a grown sweep keeps its finished trials


def test_ns_train_sp_axis_and_dataparser_last():
    spec = spec_from_dict({"command": "ns-train neus-hashgrid --max-num-iterations 5", "data": "blender-data --data d",
                           "grid": {"--pipeline.model.sdf-field.max-res": [64, 128]}})
    trials = expand(spec)
    assert len(trials) == 4
    for t in trials:
        assert t.argv[-3:] == ["blender-data", "--data", "d"]
        i = t.argv.index("--pipeline.model.sp.enabled")
        assert t.argv[i + 1] == str(t.sp)
    pairs = expand(spec_from_dict({"command": "ns-train neus-hashgrid", "data": "blender-data --data d",
                                   "sp_methods": ["neus-hashgrid", "sp-neus-hashgrid"]}))
    assert [t.argv[1] for t in pairs] == ["neus-hashgrid", "sp-neus-hashgrid"]


def test_sample_is_a_seeded_random_subset_and_sp_only_axes_share_baselines():
    grid = {"lr": [1, 2, 3], "b": [1, 2, 3], "sp.alpha0": [0.01, 0.03]}
    full = expand(spec_from_dict({"command": "sp-fit pointcloud m.ply", "grid": grid, "sp_only": ["sp.alpha0"]}))
    assert sum(t.sp for t in full) == 18 and sum(not t.sp for t in full) == 9  # one baseline per (lr, b)
    assert all(t.params["--sp.alpha0"] == "-" and "--sp.alpha0" not in t.argv for t in full if not t.sp)
    some = expand(spec_from_dict({"command": "sp-fit pointcloud m.ply", "grid": grid, "sample": 4, "sample_seed": 3}))
    again = expand(spec_from_dict({"command": "sp-fit pointcloud m.ply", "grid": grid, "sample": 4, "sample_seed": 3}))
    assert len(some) == 8 and [t.key for t in some] == [t.key for t in again]
    other = expand(spec_from_dict({"command": "sp-fit pointcloud m.ply", "grid": grid, "sample": 4, "sample_seed": 4}))
    assert [t.key for t in other] != [t.key for t in some]


@pytest.mark.parametrize("raw,message", [
    ({"command": "python train.py"}, "must start with"),
    ({"command": "ns-train neus-hashgrid"}, "data: ns-train needs a dataparser"),
    ({"command": "sp-fit pointcloud m.ply", "data": "blender-data"}, "only ns-train"),
    ({"command": "sp-fit pointcloud m.ply", "grid": {"lr": []}}, "has no values"),
    ({"command": "sp-fit pointcloud m.ply", "grid": {"lr": [1, 1]}}, "repeats a value"),
    ({"command": "sp-fit pointcloud m.ply", "grid": {"lr": [1], "--lr": [2]}}, "listed twice"),
    ({"command": "sp-fit pointcloud m.ply", "success": ["psnr is big"]}, "METRIC OP VALUE"),
    ({"command": "sp-fit pointcloud m.ply", "sp_only": ["alpha"]}, "not in the grid"),
    ({"command": "sp-fit pointcloud m.ply", "colour": 1}, "unknown field"),
])
def test_bad_specs_name_the_problem(raw, message):
    with pytest.raises(SpecError, match=message):
        expand(spec_from_dict(raw))


def test_spec_files_yaml_and_json(tmp_path):
    (tmp_path / "s.yaml").write_text("command: sp-fit pointcloud m.ply\ngrid:\n  lr: [1e-3, 1e-2]\nsp: on\n")
    (tmp_path / "s.json").write_text(json.dumps({"command": ["sp-fit", "pointcloud", "m.ply"], "grid": {"lr": ["1e-3", "1e-2"]}, "sp": "on"}))
    assert [t.key for t in expand(load_spec(tmp_path / "s.yaml"))] == [t.key for t in expand(load_spec(tmp_path / "s.json"))]
    with pytest.raises(SpecError, match="does not exist"):
        load_spec(tmp_path / "missing.yaml")


def test_success_criteria_and_soundness():
    ok = {"status": "ok", "metrics": {"psnr": 25.0, "sound": 1.0}}
    assert succeeded(ok, ["psnr >= 24", "sound == 1"]) is True
    assert succeeded(ok, ["psnr > 25"]) is False
    assert succeeded({"status": "failed", "metrics": {}}, ["psnr >= 0"]) is False
    assert succeeded(ok, []) is None
    assert is_sound(1.0, 0.10, 0.10) and not is_sound(2.0, 0.10, 0.10)  # a second sheet
    assert not is_sound(1.0, 0.9, 0.10)  # negative nearly everywhere


def test_cli_bad_spec_is_one_line_and_exit_2(sp_sweep, tmp_path):
    (tmp_path / "s.yaml").write_text("command: python train.py\n")
    proc = subprocess.run([sp_sweep, str(tmp_path / "s.yaml"), "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"sp-sweep: error: {tmp_path / 's.yaml'}: command starts with 'python'")
    proc = subprocess.run([sp_sweep, "--command", "sp-fit pointcloud m.ply", "--grid", "lr", "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "FLAG=V1,V2" in proc.stderr


README_GRID = ["--command", "sp-fit pointcloud bunny.ply --steps 300", "--grid", "lr=3e-4,1e-3,3e-3",
               "--grid", "encoding.max-resolution=256,1024,2048", "--success", "sound == 1"]


def test_cli_grid_given_twice_merges_both_axes(sp_sweep, tmp_path):
    """The README's two --grid flags: both axes (3 x 3 points, paired); tyro kept only the last one."""
    proc = subprocess.run([sp_sweep, *README_GRID, "--out", str(tmp_path / "o"), "--dry-run"],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "18 trials: 0 finished already (skipped), 18 to run" in proc.stdout
    listed = [ln for ln in proc.stdout.splitlines() if " pending " in ln]
    assert len(listed) == 18 and all("lr=" in ln and "encoding.max-resolution=" in ln for ln in listed)


def test_cli_same_grid_flag_twice_is_refused_in_one_line(sp_sweep, tmp_path):
    proc = subprocess.run([sp_sweep, "--command", "sp-fit pointcloud m.ply", "--grid", "lr=1e-3", "--grid", "lr=1e-2",
                           "--out", str(tmp_path / "o"), "--dry-run"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stdout + proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("sp-sweep: error: --grid lr is given twice") and "lr=1e-3,1e-2" in line
    assert not (tmp_path / "o").exists()


def test_a_trials_device_is_part_of_what_it_is(tmp_path):
    """--gpus-per-trial decides the device unless the command names one; a result from another device
    is not a finished trial of this sweep (a CPU folder resumed on GPUs would have skipped every trial)."""
    from sp_plugins.sweeps.report import load_results, other_devices

    cpu, gpu = expand(spec_from_dict(FIT)), expand(spec_from_dict(FIT), gpus=1)
    assert {t.device for t in cpu} == {"cpu"} and {t.device for t in gpu} == {"cuda"}
    assert [t.key for t in cpu] == [t.key for t in gpu]  # the command line is the same: the device tells them apart
    pinned = expand(spec_from_dict(dict(FIT, command=FIT["command"] + " --device cpu")), gpus=1)
    assert {t.device for t in pinned} == {"cpu"}
    ns = spec_from_dict({"command": "ns-train neus-hashgrid --machine.device-type=cuda", "data": "blender-data --data d"})
    assert {t.device for t in expand(ns)} == {"cuda"}
    for t in cpu[:3]:  # results as a CPU sweep leaves them: one of them from before results named their device
        (tmp_path / t.key).mkdir()
        result = {"key": t.key, "status": "ok", "metrics": {}, **({"device": "cpu"} if t is not cpu[0] else {})}
        (tmp_path / t.key / "result.json").write_text(json.dumps(result))
    assert set(load_results(tmp_path, cpu)) == {t.key for t in cpu[:3]} and other_devices(tmp_path, cpu) == {}
    assert load_results(tmp_path, gpu) == {} and other_devices(tmp_path, gpu) == {"cpu": 3}


def test_cli_address_auto_without_a_cluster_is_one_line_and_leaves_nothing(sp_sweep, tmp_path):
    import psutil

    if any(p.info["name"] == "raylet" for p in psutil.process_iter(["name"])):
        pytest.skip("a Ray instance runs on this machine (another sweep?): --address auto would join it")
    proc = subprocess.run([sp_sweep, "--command", "sp-fit pointcloud m.ply", "--out", str(tmp_path / "o"), "--address", "auto"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stdout + proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("sp-sweep: error: --address auto: no Ray cluster answered") and "ray start --head" in line
    assert not (tmp_path / "o").exists()
