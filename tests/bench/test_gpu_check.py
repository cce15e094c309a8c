"""bench/gpu_check.py's CPU-side pieces: it skips in one line without CUDA, parses its options,
writes strict JSON, and its agreement check tells tcnn's layout from a wrong one."""

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from sp_plugins.encodings import HashGrid
from sp_plugins.encodings.tcnn_layout import TcnnLayoutEncoding

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "gpu_check.py"


@pytest.fixture(scope="module")
def gpu_check():
    spec = importlib.util.spec_from_file_location("gpu_check_under_test", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: the check would run")
def test_without_cuda_it_skips_in_one_line_and_exits_0(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "report")], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0
    assert proc.stdout.strip().splitlines() == ["gpu_check: skipped: no CUDA device (torch.cuda.is_available() is False); "
                                                "run it on a machine with an NVIDIA GPU"]
    assert "Traceback" not in proc.stderr and not (tmp_path / "report").exists()


def test_options(gpu_check, capsys):
    args = gpu_check.parse_args([])
    assert args.parts == ["grid", "neus", "fit"] and args.neus_steps == 300 and args.fit_steps == 300
    args = gpu_check.parse_args(["--parts", "fit", "--fit-steps", "50", "--out", "x"])
    assert args.parts == ["fit"] and args.fit_steps == 50 and args.out == Path("x")
    for bad in (["--fit-steps", "0"], ["--parts", "nerf"], ["--tolerance", "-1"]):
        with pytest.raises(SystemExit) as exc:
            gpu_check.parse_args(bad)
        assert exc.value.code == 2
    assert "--fit-steps must be at least 1" in capsys.readouterr().err
    assert gpu_check.cuda_skip_reason("cuda") is not None or torch.cuda.is_available()


def test_agreement_against_the_tcnn_layout_standin(gpu_check):
    torch.manual_seed(0)
    grid = HashGrid(num_levels=4, features_per_level=2, log2_hashmap_size=9, base_resolution=4, per_level_scale=1.8,
                    backend="torch", init_scale=1.0)
    standin = TcnnLayoutEncoding(3, grid.tcnn_config())
    with torch.no_grad():
        standin.params.copy_(grid.table.reshape(-1))
    x = torch.rand(400, 3)
    good = gpu_check.agreement(grid, standin, x, tolerance=1e-4)
    assert good["ok"] and good["output"]["relative"] < 1e-5 and good["input_gradient"]["relative"] < 1e-4
    assert good["output"]["scale"] > 0.1
    with torch.no_grad():
        standin.params.copy_(grid.table.roll(1, 0).reshape(-1))  # a wrong layout must fail the check
    bad = gpu_check.agreement(grid, standin, x, tolerance=1e-2)
    assert not bad["ok"] and bad["output"]["relative"] > 1e-2


def test_grid_part_says_why_it_skips_without_tcnn(gpu_check):
    if torch.cuda.is_available():
        pytest.skip("CUDA here")
    result = gpu_check.check_grid("cuda", 16, 1, 1e-2)
    assert result["status"] == "skipped" and "tinycudann" in result["reason"]


def test_report_is_strict_json_with_a_summary(gpu_check, tmp_path):
    report = {
        "machine": gpu_check.machine_report(None),
        "grid": {"status": "ok", "agreement": {"output": {"relative": 2e-4}, "input_gradient": {"relative": 1e-3}, "tolerance": 1e-2},
                 "speed": {"fit_torch_over_tcnn": 3.5, "eikonal_torch_over_tcnn": float("nan"), "tcnn": {"eikonal": {"error": "x"}}}},
        "neus": {"status": "failed", "seconds_per_step": 0.05, "peak_gpu_mib_over_start": 812.0},
        "fit": {"status": "ok", "seconds_per_step": 0.01, "peak_gpu_mib_over_start": 300.0, "chamfer": float("inf")},
    }
    path = gpu_check.write_report(tmp_path / "deep" / "gpu_check.json", report)
    data = json.loads(path.read_text())  # strict: NaN / inf would not parse back as numbers
    del report["grid"]["speed"]["eikonal_torch_over_tcnn"]  # a failed timing has no ratio
    assert data["fit"]["chamfer"] is None and data["grid"]["speed"]["eikonal_torch_over_tcnn"] is None
    assert data["machine"]["torch"] == torch.__version__
    lines = gpu_check.summary_lines(report)
    assert lines[0].startswith("grid: ok: tcnn vs torch output 2.00e-04") and "fit 3.50x, eikonal n/a" in lines[0]
    assert lines[1] == "neus: failed, 0.050 s/step, peak GPU +812 MiB"


def test_neus_command_trains_on_cuda_from_the_scene(gpu_check, tmp_path):
    cmd = gpu_check.neus_command(tmp_path / "scene", tmp_path / "out", 300, "cuda")
    assert cmd[1] == "sp-neus-hashgrid" and cmd[cmd.index("--machine.device-type") + 1] == "cuda"
    assert cmd[cmd.index("--max-num-iterations") + 1] == "300" and cmd[-1] == str(tmp_path / "scene" / "blender")
