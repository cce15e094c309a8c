"""``--device`` on sp-fit and sp-demo, run as a user runs them (console scripts in subprocesses)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import trimesh
from trimesh.exchange.ply import export_ply

BIN = Path(sys.executable).parent
ENV = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
TINY = ["--encoding.levels", "4", "--encoding.log2-table-size", "12", "--encoding.base-resolution", "8",
        "--encoding.max-resolution", "64", "--hidden", "16", "--mesh-resolution", "24", "--refine", "1",
        "--metric-points", "2000", "--n-points", "3000", "--surface-batch", "128", "--space-batch", "128"]


def run(tool, *args, cwd):
    return subprocess.run([str(BIN / tool), *map(str, args)], capture_output=True, text=True, env=ENV, cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def mesh_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("in") / "sphere.ply"
    path.write_bytes(export_ply(trimesh.creation.icosphere(2, radius=1.0)))
    return path


def test_sp_fit_device_cpu_trains_and_reports_its_stages(tmp_path, mesh_path):
    result = run("sp-fit", "pointcloud", mesh_path, "--out", tmp_path / "run", "--steps", "4", "--device", "cpu", *TINY, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["device"] == "cpu" and metrics["steps"] == 4
    for said in ("meshing: the field on a 24^3 grid ...", "marching cubes", "measuring: Chamfer", "largest component", "writing"):
        assert said in result.stderr, said  # no silent minute after the progress bar
    assert "done in" in result.stderr


@pytest.mark.parametrize("tool, device, says", [
    ("sp-fit", "cuda", "CUDA is not available on this machine; use --device cpu"),
    ("sp-demo", "cuda", "CUDA is not available on this machine; use --device cpu"),
    ("sp-fit", "tpu", "not a device; use auto, cpu, cuda, cuda:N or mps"),
])
def test_an_unusable_device_is_one_line_exit_2(tool, device, says, tmp_path, mesh_path):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    args = ["pointcloud", mesh_path, "--steps", "2"] if tool == "sp-fit" else ["--steps", "12"]
    result = run(tool, *args, "--out", tmp_path / "run", "--device", device, cwd=tmp_path)
    assert result.returncode == 2
    assert says in result.stderr and f"--device {device}" in result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert not (tmp_path / "run").exists()  # refused before anything was written
