"""``pip install sp-plugins`` beside sdfstudio must leave sdfstudio's ``nerfstudio`` in place."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests.helpers.sdf_configs import env

ROOT = Path(__file__).resolve().parents[2]


def planned_installs(tmp_path: Path, target: str) -> dict:
    """What ``pip install TARGET`` would install into this (sdfstudio) venv: pip's own resolver
    in ``--dry-run`` mode, against the packages installed here."""
    report = tmp_path / "report.json"
    cmd = [sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--report", str(report), target]
    proc = subprocess.run(cmd, env=env(), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    items = json.loads(report.read_text())["install"]
    return {item["metadata"]["name"].lower(): item["metadata"]["version"] for item in items}


def test_base_install_keeps_sdfstudio(tmp_path):
    plan = planned_installs(tmp_path, str(ROOT))
    assert "sp-plugins" in plan and "nerfstudio" not in plan, plan


def test_nerfstudio_1x_is_only_an_extra():
    """The same check from the metadata side: every nerfstudio requirement sits behind the extra."""
    from importlib.metadata import requires

    from packaging.requirements import Requirement

    host = [Requirement(r) for r in requires("sp-plugins") or [] if Requirement(r).name == "nerfstudio"]
    assert host and all(r.marker is not None and r.marker.evaluate({"extra": "nerfstudio"}) for r in host)
    assert not any(r.marker.evaluate({"extra": ""}) for r in host)
