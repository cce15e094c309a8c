"""``sp-sweep`` of a tiny ``sp-fit`` task as a user runs it: a local Ray with 2 CPUs, a sweep of a
grid point that fits and one that ``sp-fit`` refuses, which records the failure and goes on; then a
rerun that starts nothing (every trial has finished), and a grown grid whose plan (``--dry-run``,
the same pending list a run hands to Ray) holds only the new point; no Ray processes or temporary
files left behind (see ``run_sweep``). The README's cluster line (``--address auto --gpus-per-trial
1``) on that folder of CPU trials is refused in one line before any Ray is reached: they are not its
finished trials. (One Ray start here: the README's two sweeps start Ray again, ``tests/test_readme.py``.)"""

from __future__ import annotations

import math
import subprocess

import pytest

FIT_TINY = ("--steps 8 --n-points 2000 --surface-batch 128 --space-batch 128 --encoding.levels 4 "
            "--encoding.log2-table-size 10 --encoding.base-resolution 8 --hidden 16 --mesh-resolution 24 "
            "--refine 1 --metric-points 2000")
NC_RULE, CHAMFER_RULE = "normal_consistency >= 0.6", "chamfer < 0.3"


@pytest.mark.timeout(1800)  # about a minute and a half on 2 idle cores; Ray's start alone took a minute at load 10
def test_sp_fit_sweep_records_a_failed_trial_and_a_restart_skips_finished_trials(run_sweep, rows, sweep_mesh, tmp_path,
                                                                                 sp_sweep):
    out = tmp_path / "sweep"
    # With --geometric-init the 8 steps leave a sphere (normal consistency about 0.84-0.96, Chamfer
    # 0.03-0.09 for seeds 0 and 1); without a mesh the rule fails (consistency 0, Chamfer null).
    # Grid point 4 is one sp-fit refuses (max 4 < base 8): recorded as failed, the sweep goes on.
    spec = {"command": f"sp-fit pointcloud {sweep_mesh} {FIT_TINY} --geometric-init",
            "grid": {"encoding.max-resolution": [32, 4]},
            "success": [NC_RULE, CHAMFER_RULE], "metric": "fscore"}
    proc = run_sweep(spec, out)
    assert "4 trials: 0 finished already (skipped), 4 to run" in proc.stdout
    assert "4 of 4 trials finished, 2 failed" in proc.stdout
    table = rows(out)
    assert len(table) == 4 and sorted(r["sp"] for r in table) == ["SP", "SP", "baseline", "baseline"]
    for r in table:
        if r["max-resolution"] == "32":
            assert r["status"] == "ok" and math.isfinite(float(r["wall_seconds"])) and float(r["sound"]) in (0.0, 1.0)
            assert float(r["success"]) == 1, r  # the rules hold, with a margin
            assert float(r["normal_consistency"]) >= 0.7 and float(r["chamfer"]) < 0.2, r
        else:
            assert r["status"] == "failed" and "base_resolution <= max_resolution" in r["error"] and float(r["success"]) == 0
    md = (out / "results.md").read_text()
    assert all(md.count(r["trial"]) == 1 for r in table)  # one row per trial
    assert f"success ({NC_RULE} and {CHAMFER_RULE}): baseline 1/2 (50%), SP 1/2 (50%)" in md
    assert (out / "histogram.png").stat().st_size > 1000

    # the same sweep again: every trial (the failed ones too) has finished, nothing runs, no Ray starts
    done = {p: p.stat().st_mtime_ns for p in out.glob("trials/*/result.json")}
    assert len(done) == 4
    proc = run_sweep(spec, out)
    assert "4 trials: 4 finished already (skipped), 0 to run" in proc.stdout, proc.stdout
    assert {p: p.stat().st_mtime_ns for p in done} == done, "a finished trial was run again"
    assert len(list((out / "ray").glob("run-*"))) == 1, "a second Ray run was started with nothing to run"

    # the grid grows by one point: the plan holds only its two trials, beside the four finished ones
    spec["grid"]["encoding.max-resolution"].append(16)
    proc = run_sweep(spec, out, "--dry-run")
    assert "6 trials: 4 finished already (skipped), 2 to run" in proc.stdout, proc.stdout
    plan = [line.split() for line in proc.stdout.splitlines() if line.startswith("  ")]
    assert sorted(p[1] for p in plan) == ["done"] * 4 + ["pending"] * 2, plan
    assert all(p[0] in {r["trial"] for r in table} for p in plan if p[1] == "done"), plan
    assert {p: p.stat().st_mtime_ns for p in done} == done

    # the same study on GPUs into this folder of CPU trials (it used to skip all four as finished)
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    proc = subprocess.run([sp_sweep, str(tmp_path / "spec.yaml"), "--out", str(out), "--address", "auto",
                           "--gpus-per-trial", "1"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stdout + proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith(f"sp-sweep: error: {out.resolve()} holds finished trials of this sweep run elsewhere (4 on cpu)")
    assert "they run on cuda" in line and "another --out" in line and "--gpus-per-trial 0" in line
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before, "the CPU sweep's folder was touched"
