"""The real ``ns-train`` command line, once, on a tiny scene (about 10 s)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.helpers.errors import refused

NS_TRAIN = shutil.which("ns-train") or str(Path(sys.executable).parent / "ns-train")

TINY = [
    # nerfstudio's default --vis viewer, as a user runs it; the trainer exits after its last step
    "--machine.device-type", "cpu", "--max-num-iterations", "2", "--viewer.quit-on-train-completion", "True", "--timestamp", "t",
    "--steps-per-save", "2", "--logging.local-writer.enable", "False",
    "--pipeline.datamanager.train-num-rays-per-batch", "32",
    "--pipeline.model.num-samples", "16", "--pipeline.model.num-samples-importance", "8",
    "--pipeline.model.num-up-sample-steps", "1", "--pipeline.model.background-model", "none",
    "--pipeline.model.sdf-field.hidden-dim", "32", "--pipeline.model.sdf-field.hidden-dim-color", "32",
    "--pipeline.model.sdf-field.geo-feat-dim", "15", "--pipeline.model.sdf-field.log2-hashmap-size", "12",
    "--pipeline.model.sdf-field.max-res", "64", "--pipeline.model.sp.alpha0", "0.02",
]


@pytest.mark.skipif(not os.path.exists(NS_TRAIN), reason="ns-train is not installed")
def test_ns_train_cli_trains_sp_neus_hashgrid_on_blender_data(tiny_scene, tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [NS_TRAIN, "sp-neus-hashgrid", *TINY, "--output-dir", str(tmp_path), "blender-data", "--data", str(tiny_scene / "blender")]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    from tests.helpers.viewer import PORT_LINE

    assert PORT_LINE.search(proc.stdout), "the run did not start nerfstudio's viewer"
    ckpts = list(tmp_path.glob("**/nerfstudio_models/step-*.ckpt"))
    assert len(ckpts) == 1
    state = torch.load(ckpts[0], map_location="cpu", weights_only=False)["pipeline"]
    assert int(state["_model.sp.total_steps"]) == 2
    # the finest level's cell: the grid's [-2, 2] span over its max-res 64 vertices (63 cells)
    assert float(state["_model.field.fd_step"]) == pytest.approx(4.0 / 63, rel=1e-4)
    from sp_plugins.nerfstudio.components.lpips import lpips_available

    if not lpips_available():  # offline: one clear line, no download attempt, no crash
        assert (proc.stdout + proc.stderr).count("LPIPS skipped") == 1


@pytest.mark.skipif(not os.path.exists(NS_TRAIN), reason="ns-train is not installed")
def test_ns_train_reports_a_missing_data_folder_in_one_line(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    missing = tmp_path / "no-such-scene"
    cmd = [NS_TRAIN, "sp-relu-field", "--machine.device-type", "cpu", "--output-dir", str(tmp_path / "out"), "blender-data", "--data", str(missing)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    refused(proc, "ns-train", str(missing), "--data", others=True)


def test_input_error_hook_prints_one_line_and_leaves_other_errors_alone(capsys, monkeypatch):
    from sp_plugins.adapter.errors import InputError
    from sp_plugins.patches import registry

    seen = []
    monkeypatch.setattr(sys, "excepthook", lambda *exc: seen.append(exc[0]))
    with registry.scope("input_error_hook"), registry.scope("input_error_hook"):  # idempotent: one wrapper
        with pytest.raises(SystemExit) as exit_info:
            sys.excepthook(InputError, InputError("bad --data"), None)
        assert exit_info.value.code == 2 and capsys.readouterr().err.strip().endswith("error: bad --data")
        sys.excepthook(KeyError, KeyError("x"), None)
    assert seen == [KeyError]
