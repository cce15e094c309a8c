"""``./run.sh test`` without the sdfstudio environment: in CI (``CI=true``) the run fails and says
why; elsewhere pytest reports the sdfstudio tests as skipped, with the reason. Before, both exited 0
with one stderr line and pytest never saw the tests, so a CI without the host looked green."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ONE_FILE = "tests/sdfstudio/test_seam.py"


def fake_venv(tmp_path: Path) -> Path:
    """A folder run.sh takes for an installed environment: its python runs this interpreter, its
    stamp is the one run.sh writes for this checkout (so ``setup`` installs nothing)."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    python = venv / "bin" / "python"
    python.write_text(f'#!/bin/sh\nexec {sys.executable} "$@"\n')
    python.chmod(0o755)
    sha = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    (venv / ".sp-plugins-stamp").write_text(f"{sha} {TORCH_SPEC} {ROOT}\n")
    return venv


def run_sh_test(tmp_path: Path, ci: bool) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "SP_SDFSTUDIO_TESTS", "SP_SDFSTUDIO_MISSING")}
    env.update(SP_VENV=str(fake_venv(tmp_path)), SP_TORCH_SPEC=TORCH_SPEC, SP_SDFSTUDIO_VENV=str(tmp_path / "no-venv"),
               SP_SDFSTUDIO_SRC=str(tmp_path / "no-src"), SP_TEST_WORKERS="1", OMP_NUM_THREADS="1")
    if ci:
        env["CI"] = "true"
    return subprocess.run(["bash", str(ROOT / "run.sh"), "test", ONE_FILE], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=300)


TORCH_SPEC = "torch-as-installed"
"""Any fixed spec: it only enters the stamp (nothing is installed)."""
needs_libusb = pytest.mark.skipif(
    "libusb-1.0.so.0" not in subprocess.run(["sh", "-c", "ldconfig -p 2>/dev/null"], capture_output=True, text=True).stdout,
    reason="run.sh's setup would install libusb-1.0-0 (a system package) first")


def test_ci_fails_without_the_sdfstudio_environment(tmp_path):
    proc = run_sh_test(tmp_path, ci=True)
    assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert f"error: CI=true and the sdfstudio tests cannot run: no sdfstudio environment at {tmp_path / 'no-venv'}" in proc.stderr
    assert "git clone https://github.com/autonomousvision/sdfstudio" in proc.stderr


@needs_libusb
def test_elsewhere_pytest_reports_them_skipped_with_the_reason(tmp_path):
    proc = run_sh_test(tmp_path, ci=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "installing" not in out  # the stamp matched: nothing was installed
    assert "1 skipped" in proc.stdout and "passed" not in proc.stdout, proc.stdout[-2000:]
    assert ("SKIPPED [1] tests/sdfstudio/conftest.py" in proc.stdout
            and f"sdfstudio tests need sdfstudio's environment: no sdfstudio environment at {tmp_path / 'no-venv'}" in proc.stdout)
