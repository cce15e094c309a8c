"""bench/sparse_views.py at a toy size: MipNeRF, FreeNeRF-lite and MipNeRF + SP on the
DTU-like scene of a mesh file, paired (same initial weights, same rays), one resumable JSON per run,
the summary over seeds, and ``radiance_methods mipnerf --dtu-like --quick MESH``'s last line."""

import dataclasses
import json
import math
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the checkout: bench/ is not an installed package
import bench.harness.nerfstudio as ns  # noqa: E402
import bench.radiance_methods as rm  # noqa: E402
import bench.sparse_views as sv  # noqa: E402
from bench.harness import radiance as rd  # noqa: E402

TOY = rd.MipBudget(steps=4, rays=32, coarse=8, fine=8, mlp_num_layers=2, mlp_layer_width=16, head_width=8, views=3, dtu_like=True)
SP = sv.SPSetting(0.05, 0.5)
GRID = sv.SPSetting(0.05, 0.5, grid=True)
TOY_FLAGS = ["--steps", "3", "--rays", "32", "--coarse", "8", "--fine", "8", "--mlp-num-layers", "2", "--mlp-layer-width", "16",
             "--head-width", "8"]


@pytest.fixture(scope="module")
def bench_out(tmp_path_factory):
    """Outputs under a temporary folder; the DTU-like scene at 8 + 2 views of 32x24."""
    out = tmp_path_factory.mktemp("bench") / "radiance_methods"
    patch = pytest.MonkeyPatch()
    patch.setattr(rd, "OUT", out)
    real = rd.dtu_scene_dir
    patch.setattr(rd, "dtu_scene_dir", lambda scene, up_axis=None: real(scene, up_axis, views=8, test_views=2, resolution=(32, 24)))
    yield out
    patch.undo()


@pytest.fixture(scope="module")
def mesh(tmp_path_factory):
    """Any mesh file: a box with a bump, y up."""
    import trimesh

    shape = trimesh.util.concatenate([trimesh.creation.box((1.0, 0.6, 0.8)), trimesh.creation.icosphere(2, 0.35).apply_translation((0.2, 0.4, 0))])
    path = tmp_path_factory.mktemp("mesh") / "thing.ply"
    shape.export(path)
    return str(path)


@pytest.fixture(scope="module")
def group(bench_out, mesh):
    return sv.study(mesh, TOY, 0, sv.run_specs([SP, GRID]), "toy", up_axis="y")


def test_each_run_is_its_own_json_from_the_same_weights(group, bench_out):
    names = [sv.BASELINE, sv.FREENERF, SP.name, GRID.name]
    assert list(group) == names
    folder = sv.out_dir() / "toy" / group[sv.BASELINE]["group"]
    assert sorted(p.stem for p in folder.glob("*.json")) == sorted(names) and (folder / "renders.png").is_file()
    assert len({r["init_weights"] for r in group.values()}) == 1  # paired: one start for all four
    assert all(r["trained_with"] == names for r in group.values())
    base, free, sp = group[sv.BASELINE], group[sv.FREENERF], group[SP.name]
    for r in group.values():
        assert len(r["losses"]) == TOY.steps and r["budget"]["views"] == 3
        for key in ("psnr", "psnr_object", "ssim", "ssim_object"):
            assert math.isfinite(r[key]), (r["run"], key)
        assert "lpips" not in r  # no AlexNet weights offline
    assert base["psnr_object"] != pytest.approx(base["psnr"], abs=1e-3)
    assert base["alphas"] == [0.0] * TOY.steps and sp["alphas"][0] == pytest.approx(0.05)
    assert free["alphas"][0] == 0.0 and free["freenerf"]["occ_reg_range_used"] == 1  # 10 of 128 -> 1 of 8
    # same weights and rays at step 0: only FreeNeRF's mask and term, or SP's offsets, tell them apart
    assert free["losses"][0] != base["losses"][0] and sp["losses"][0] != base["losses"][0]


def test_a_later_process_adds_runs_without_retraining_and_stays_paired(group, bench_out, mesh, monkeypatch):
    folder = sv.out_dir() / "toy" / group[sv.BASELINE]["group"]
    before = {p.name: p.stat().st_mtime_ns for p in folder.glob("*.json")}
    built = []
    real_run = ns.Run

    def counting(name, config, seed):
        built.append(name)
        return real_run(name, config, seed)

    monkeypatch.setattr(ns, "Run", counting)
    wider = sv.SPSetting(0.2, 0.5)
    more = sv.study(mesh, TOY, 0, sv.run_specs([SP, GRID, wider]), "toy", up_axis="y")
    assert built == [wider.name]  # the four finished runs are read back, not trained again
    assert {p.name: p.stat().st_mtime_ns for p in folder.glob("*.json") if p.name in before} == before
    assert more[wider.name]["init_weights"] == group[sv.BASELINE]["init_weights"]
    # a baseline trained alone, in another group of runs, sees the same rays: identical losses
    alone = sv.study(mesh, TOY, 0, sv.run_specs([], freenerf=None), "alone", up_axis="y")
    assert alone[sv.BASELINE]["losses"] == group[sv.BASELINE]["losses"]


def test_a_group_whose_runs_started_apart_is_refused(group, bench_out, mesh):
    folder = sv.out_dir() / "toy" / group[sv.BASELINE]["group"]
    path = folder / f"{SP.name}.json"
    saved = path.read_text()
    path.write_text(json.dumps({**json.loads(saved), "init_weights": "0" * 16}))
    try:
        with pytest.raises(RuntimeError, match="started from different weights"):
            sv.study(mesh, TOY, 0, sv.run_specs([SP, GRID]), "toy", up_axis="y")
    finally:
        path.write_text(saved)


def test_quick_prints_the_three_psnrs_last(bench_out, mesh, capsys):
    rm.main(["mipnerf", "--dtu-like", "--quick", mesh, "--up-axis", "y", "--tag", "toy-quick", *TOY_FLAGS])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert re.fullmatch(r"baseline PSNR \d+\.\d\d, SP PSNR \d+\.\d\d, FreeNeRF PSNR \d+\.\d\d \(object\)", last), last
    (result,) = [json.loads(p.read_text()) for p in (sv.out_dir() / "toy-quick").glob(f"*/{sv.BASELINE}.json")]
    assert (result["budget"]["views"], result["budget"]["lr"], result["budget"]["steps"]) == (3, 2e-3, 3)  # QUICK, flags win
    sp = json.loads(next((sv.out_dir() / "toy-quick").glob("*/sp*.json")).read_text())
    assert sp["sp"] == {"alpha0": 1.0, "end": 0.333, "grid": False}  # the sparse-view setting (sv.SPARSE)
    assert last.startswith(f"baseline PSNR {result['psnr_object']:.2f},")


def test_summary_pairs_seeds_and_counts_those_ahead_beyond_the_baseline_spread():
    def result(run, seed, obj):
        return {"scene": "/x/spot.ply", "run": run, "seed": seed, "budget": {"views": 3}, "psnr": obj + 4, "psnr_object": obj,
                "ssim": 0.5, "ssim_object": 0.7, "median_step_s": 0.2}

    rows = sv.summary([result(sv.BASELINE, 0, 10.0), result(sv.BASELINE, 1, 11.0), result("sp[1@0.3]", 0, 12.0),
                       result("sp[1@0.3]", 1, 11.2)]).splitlines()
    assert rows[2].startswith(f"| spot | 3 | {sv.BASELINE} | 2 | 14.50 ± 0.71 | 10.50 ± 0.71 |  |  |")
    # paired differences +2.0 and +0.2: mean 1.10, sd 1.273, 95% t interval with 1 degree of freedom
    # 1.10 -+ 12.706 * 1.273 / sqrt(2) = [-10.34, +12.54]; the baseline's seed spread is 0.71: one seed ahead beyond it
    assert rows[3].startswith("| spot | 3 | sp[1@0.3] | 2 | 15.60 ± 0.57 | 11.60 ± 0.57 | +1.10 [-10.34, +12.54] | 1 / 2 |")
    # whole-image SSIM: the same on every run here: a zero difference, and no seed ahead beyond the spread (0)
    assert rows[3].split(" | ")[8:11] == ["0.50 ± 0.00", "+0.00 [+0.00, +0.00]", "0 / 2"]


@pytest.mark.parametrize("text", ["0.4", "0.4@0", "0.4@1.5", "-1@0.3", "0.4@0.3:mesh"])
def test_sp_settings_are_parsed_or_refused_in_one_line(text):
    import argparse

    with pytest.raises(argparse.ArgumentTypeError, match="ALPHA0@END"):
        sv.SPSetting.parse(text)
    assert sv.SPSetting.parse("0.04@0.333:grid") == sv.SPSetting(0.04, 0.333, True)


def test_the_group_key_ignores_the_old_studys_sp_fields():
    assert sv.group_name("spot", TOY, 0) == sv.group_name("spot", dataclasses.replace(TOY, alpha0=0.5, end=7), 0)
    assert sv.group_name("spot", TOY, 0) != sv.group_name("spot", TOY, 1)
