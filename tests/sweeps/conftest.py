"""Shared fixtures of the sweep tests: a tiny scene, a tiny mesh, the sp-sweep command and its runner."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import psutil
import pytest
import trimesh
import yaml
from trimesh.exchange.ply import export_ply


@pytest.fixture(scope="session")
def sweep_scene(tmp_path_factory) -> Path:
    """8 training views of a 32x32 sphere (scene root: blender/, sdfstudio/, gt_mesh.ply)."""
    from sp_plugins.data import make_tiny_scene

    return make_tiny_scene(tmp_path_factory.mktemp("sweep-scene") / "sphere", mesh="sphere").root


@pytest.fixture(scope="session")
def sweep_mesh(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sweep-mesh") / "sphere.ply"
    path.write_bytes(export_ply(trimesh.creation.icosphere(2, radius=3.0)))
    return path


@pytest.fixture(scope="session")
def sp_sweep() -> str:
    path = Path(sys.executable).parent / "sp-sweep"
    if not path.exists() and shutil.which("sp-sweep") is None:
        pytest.skip("sp-sweep is not installed (pip install -e '.[sweeps]')")
    return str(path if path.exists() else shutil.which("sp-sweep"))


@pytest.fixture
def run_sweep(sp_sweep, tmp_path):
    """``sp-sweep SPEC --out OUT [EXTRA...]`` on a local Ray of 2 CPUs, as a user runs it; asserts it exits 0
    and leaves no Ray process or temporary folder behind. Returns the finished process."""

    def run(spec: dict, out: Path, *extra: str) -> subprocess.CompletedProcess:
        path = tmp_path / "spec.yaml"
        path.write_text(yaml.safe_dump(spec))
        ray_tmp = Path(tempfile.mkdtemp(prefix="spt-", dir="/tmp"))  # short: Ray's socket paths are limited
        ray_tmp.rmdir()  # a fresh name: sp-sweep makes the folder when it starts Ray and removes it at the end
        env = dict(os.environ, OMP_NUM_THREADS="1")
        try:
            proc = subprocess.run([sp_sweep, str(path), "--out", str(out), "--num-cpus", "2", "--cpus-per-trial", "1",
                                   "--ray-temp-dir", str(ray_tmp), "--timeout", "400", *extra],
                                  capture_output=True, text=True, timeout=1500, env=env, cwd=tmp_path)
            left = [p.pid for p in psutil.process_iter(["cmdline"]) if any(str(ray_tmp) in a for a in (p.info["cmdline"] or []))]
            assert not left, f"Ray processes left running: {left}"
            assert not ray_tmp.exists(), "Ray's temporary folder was left behind"
        finally:
            subprocess.run(["rm", "-rf", str(ray_tmp)])
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        return proc

    return run


def result_rows(out: Path) -> list:
    """The rows of a sweep's ``results.csv``."""
    with open(out / "results.csv") as f:
        return list(csv.DictReader(f))


@pytest.fixture
def rows():
    return result_rows
