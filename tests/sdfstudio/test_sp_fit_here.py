"""``sp-fit`` is a base command (no host needed), so ``pip install -e ".[sdfstudio]"`` installs it beside
sdfstudio too: it must work there, with sdfstudio's pins (tyro 0.9.1), as the README writes it."""

from __future__ import annotations

import importlib.resources
import json
import math

from tests.helpers.sdf_configs import run


def _spot() -> str:
    return str(importlib.resources.files("sp_plugins.data.assets") / "spot.ply")


def test_sp_fit_help_lists_its_tasks():
    """tyro 0.9.1 has no ``FlagCreatePairsOff``: reading it at import crashed every ``sp-fit`` here."""
    proc = run(["sp-fit", "--help"], cwd=None)
    assert all(task in proc.stdout for task in ("pointcloud", "image", "sdf")), proc.stdout


def test_sp_fit_pointcloud_fits_and_measures_the_mesh(tmp_path):
    """The README's point-cloud fit, shortened with the flags it names (``--steps``, ``--mesh-resolution``):
    a mesh and its Chamfer distance, which needs ``rtree`` (trimesh's nearest-point queries import it
    lazily; it is one of sp-plugins' own dependencies, since no host's brings it here). ``--no-sp`` parses."""
    run(["sp-fit", "pointcloud", _spot(), "--out", "runs/spot", "--steps", "40", "--mesh-resolution", "32"], cwd=tmp_path)
    metrics = json.loads((tmp_path / "runs/spot/metrics.json").read_text())
    assert metrics["sp"]["enabled"] is True and metrics["steps"] == 40
    assert math.isfinite(metrics["chamfer"]) and metrics["chamfer"] < 0.05 and metrics["fscore"] > 0.5
    run(["sp-fit", "pointcloud", _spot(), "--out", "runs/spot-base", "--no-sp", "--steps", "2", "--mesh-resolution", "32"],
        cwd=tmp_path)
    assert json.loads((tmp_path / "runs/spot-base/metrics.json").read_text())["sp"]["enabled"] is False
