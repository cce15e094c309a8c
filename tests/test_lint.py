"""The lint and type checks: ``ruff check`` and ``mypy`` with the settings in pyproject.toml
(``[tool.ruff]``, ``[tool.mypy]``) find nothing. Both run from the checkout's root, as
.pre-commit-config.yaml runs them. They are in the dev extra (``./run.sh setup`` installs it): a missing
tool fails these tests, it does not skip them."""

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_tool(module: str, *args: str) -> subprocess.CompletedProcess:
    assert importlib.util.find_spec(module) is not None, (
        f"{module} is not installed in {sys.prefix}: it is in the dev extra (pip install -e '.[dev]', or ./run.sh setup)"
    )
    return subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def report(result: subprocess.CompletedProcess) -> str:
    return f"exit status {result.returncode}\n{result.stdout}{result.stderr}"


def test_ruff_finds_nothing():
    result = run_tool("ruff", "check", "--no-cache", "--output-format", "concise")
    assert result.returncode == 0, report(result)


def test_mypy_finds_nothing():
    result = run_tool("mypy")
    # one line, "Success: no issues found in N source files": no error, and no note either
    lines = result.stdout.strip().splitlines()
    assert result.returncode == 0 and len(lines) == 1 and lines[0].startswith("Success: no issues found"), report(result)


def test_ruff_lints_every_python_file_of_the_checkout():
    """A new folder of Python files must be added to ``[tool.ruff] include``, else ruff never sees it."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: no list of its files")
    tracked = subprocess.run(["git", "ls-files", "*.py"], cwd=ROOT, capture_output=True, text=True, check=True)
    listed = run_tool("ruff", "check", "--no-cache", "--show-files")
    assert listed.returncode == 0, report(listed)
    linted = {Path(line).resolve() for line in listed.stdout.splitlines() if line.strip()}
    missed = sorted(name for name in tracked.stdout.splitlines()
                    if (ROOT / name).is_file() and (ROOT / name).resolve() not in linted)
    assert not missed, f"not linted (add them to [tool.ruff] include in pyproject.toml): {missed}"
