"""sp-gpu-check's CPU paths: a CUDA build that sees no GPU fails (it cannot pass by accident),
``--device cpu --quick`` runs every part's CPU path and says what it skipped, the deadline holds,
and its comparisons judge what they should."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from sp_plugins.cli import gpu_check
from sp_plugins.encodings import HashGrid
from sp_plugins.encodings.tcnn_layout import TcnnLayoutEncoding

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "bench" / "gpu_check.py"


def run(args, tmp_path, timeout=600):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=timeout)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: the check would run")
@pytest.mark.parametrize("how", ["sp-gpu-check", "bench/gpu_check.py"])
def test_without_a_gpu_the_cuda_check_fails_in_one_line_naming_the_build_and_driver(tmp_path, how):
    """... and pointing at what a machine without a GPU can run (the console command as the README writes
    it, and the checkout's thin caller)."""
    command = [str(Path(sys.executable).parent / "sp-gpu-check")] if how == "sp-gpu-check" else [sys.executable, str(SCRIPT)]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run([*command, "--out", str(tmp_path / "report")], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=600)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    (line,) = proc.stdout.strip().splitlines()
    if torch.version.cuda is not None:
        assert f"is a CUDA {torch.version.cuda} build but sees no CUDA device" in line and ("NVIDIA driver" in line or "nvidia-smi" in line)
    else:
        assert "CPU-only build" in line
    assert line.startswith("sp-gpu-check: error: ") and "Traceback" not in proc.stderr and not (tmp_path / "report").exists()
    assert line.endswith(": sp-gpu-check --device cpu --quick"), line


@pytest.fixture(scope="module")
def cpu_quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("gpu-check")
    proc = run(["-m", "sp_plugins.cli.gpu_check", "--device", "cpu", "--quick", "--out", str(out)], out)
    return proc, json.loads((out / "gpu_check.json").read_text())


def test_cpu_quick_runs_every_part_and_says_what_it_skipped(cpu_quick):
    proc, report = cpu_quick
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    parts = report["parts"]
    assert {p: parts[p]["status"] for p in gpu_check.PARTS} == {p: "ok" for p in gpu_check.PARTS}
    assert "--device cpu: no GPU part runs" in report["skipped"][0] and report["machine"]["torch"] == torch.__version__
    grid = parts["grid"]
    assert grid["against"].startswith("tcnn_layout stand-in") and any(s.startswith("tcnn: ") for s in grid["skipped"])
    assert grid["agreement"]["ok"] and grid["autocast"]["dtype"] == "torch.bfloat16"
    runs = parts["runs"]["runs"]
    assert set(runs) == {"neus-hashgrid", "sp-neus-hashgrid", "nerfacto", "sp-train nerfacto", "sp-nerfacto"}
    for name, r in runs.items():
        assert r["seconds_per_step"] > 0 and r["finite"] and r["syncs"]["steps"] >= 1, name
        assert r["sp_alpha"] is None or (r["sp_alpha"] > 0) == name.startswith("sp-"), name
    assert set(parts["runs"]["sp_overhead"]) == {"neus-hashgrid", "nerfacto"}
    assert any("torch grid" in s for s in parts["runs"]["skipped"]) and any("CUDA only" in s for s in parts["runs"]["skipped"])
    resume = parts["checkpoint"]["resume"]
    assert resume["ok"] and resume["adam_moments_match"] and resume["continued_from_step"] > 0
    assert any("--quick" in s for s in parts["checkpoint"]["skipped"])
    assert parts["fit"]["syncs"]["ours"] == {} and parts["fit"]["timer_ok"] and parts["fit"]["finite"]
    repeat = parts["repeat"]  # the same fit twice, bitwise: on a CPU it must match
    assert repeat["repeats"] and repeat["differing"] == {} and repeat["tensors"] >= 4 and repeat["hash_grid"] == "torch"
    assert repeat["deterministic_kernels"] and "bit-identical" in proc.stdout
    assert all(r["syncs"]["ours"] == {} for r in runs.values())  # counted along the GPU's branches
    assert any(site.startswith("nerfstudio/") for site in runs["nerfacto"]["syncs"]["host"])  # the host's are reported
    assert report["seconds"] < report["deadline_s"]
    printed = proc.stdout
    assert "skipped tcnn: tiny-cuda-nn runs on CUDA only" in printed and "; report -> " in printed


def test_the_deadline_includes_start_up_and_stops_everything(tmp_path):
    proc = run(["-m", "sp_plugins.cli.gpu_check", "--device", "cpu", "--quick", "--deadline", "1", "--out", str(tmp_path)], tmp_path, 120)
    assert proc.returncode == 1
    report = json.loads((tmp_path / "gpu_check.json").read_text())
    assert report.get("deadline_reached") or all("deadline" in r.get("reason", r.get("error", "")) for r in report["parts"].values())
    assert "deadline" in proc.stdout


def test_require_tcnn_makes_a_missing_tcnn_a_failure(tmp_path):
    assert gpu_check.main(["--device", "cpu", "--quick", "--parts", "grid", "--out", str(tmp_path)]) == 0
    assert gpu_check.main(["--device", "cpu", "--quick", "--parts", "grid", "--require-tcnn", "--out", str(tmp_path)]) == 1
    grid = json.loads((tmp_path / "gpu_check.json").read_text())["parts"]["grid"]
    assert grid["status"] == "failed" and grid["error"].startswith("--require-tcnn: tiny-cuda-nn runs on CUDA only")


def test_points_are_judged_by_the_fraction_over_tolerance():
    torch.manual_seed(0)
    a = torch.randn(1000, 4)
    one_off = a.clone()
    one_off[7] += 10.0  # a point the backends floor into different cells
    assert gpu_check.compare_points(a, one_off, 1e-2, 1e-2)["ok"]
    many = a.clone()
    many[:50] += 10.0
    judged = gpu_check.compare_points(a, many, 1e-2, 1e-2)
    assert not judged["ok"] and judged["fraction_over_tolerance"] == pytest.approx(0.05)


def test_agreement_against_the_tcnn_layout_standin_tells_a_wrong_layout():
    torch.manual_seed(0)
    grid = HashGrid(num_levels=4, features_per_level=2, log2_hashmap_size=9, base_resolution=4, per_level_scale=1.8,
                    backend="torch", init_scale=1.0)
    standin = TcnnLayoutEncoding(3, grid.tcnn_config())
    with torch.no_grad():
        standin.params.copy_(grid.table)
    x = torch.rand(400, 3)
    good = gpu_check.agreement(grid, standin, x, 1e-4, 1e-2, 1e-4)
    assert good["ok"] and good["table_gradient"]["cosine"] > 0.9999
    with torch.no_grad():
        standin.params.copy_(grid.table.view(grid.n_table_rows, -1).roll(1, 0).reshape(-1))  # rows off by one
    bad = gpu_check.agreement(grid, standin, x, 1e-2, 1e-2, 5e-2)
    assert not bad["ok"] and bad["output"]["fraction_over_tolerance"] > 0.5


def test_report_is_strict_json_and_the_script_is_registered(tmp_path):
    import tomllib

    report = gpu_check.Report(tmp_path / "deep" / "gpu_check.json", {"a": float("inf"), "b": [float("nan"), Path("x")]})
    report.write()
    assert json.loads(report.path.read_text()) == {"a": None, "b": [None, "x"]}
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["sp-gpu-check"] == "sp_plugins.cli.gpu_check:entrypoint" and callable(gpu_check.entrypoint)


def test_called_from_python_the_deadline_counts_from_the_call_and_never_ends_the_callers_process(tmp_path):
    """A pytest worker that has lived past --deadline must not be killed by the watchdog: called from
    Python, the deadline counts from the call and a reached deadline only records itself."""
    assert gpu_check.Deadline(1.0, since_process_start=False).remaining() > 0.5
    code = gpu_check.main(["--device", "cpu", "--quick", "--parts", "grid", "--deadline", "0.5", "--out", str(tmp_path)])
    report = json.loads((tmp_path / "gpu_check.json").read_text())
    assert code == 1 and report["parts"]["grid"]["status"] == "failed"  # cut or refused by the deadline, process alive
