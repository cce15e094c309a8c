"""``nerfbaselines train`` twice, each in a fresh process and folder, gives bit-identical checkpoints
and the same metrics: one of nerfbaselines' own methods with SP on (``nerfacto+sp``, nerfstudio's
parallel data manager under nerfbaselines' wrapper), at two torch threads with ``SP_DETERMINISTIC=1``."""

from __future__ import annotations

import json

import pytest

from tests.helpers.ns_commands import command
from tests.helpers.repeat import checkpoint, differing, floating, train_twice

pytest.importorskip("nerfbaselines")

SETTINGS = ["--set", "machine.device_type=cpu", "--set", "max_num_iterations=3",
            "--set", "pipeline.datamanager.train_num_rays_per_batch=256", "--set", "pipeline.model.eval_num_rays_per_chunk=1024",
            "--set", "pipeline.model.log2_hashmap_size=14"]


@pytest.fixture
def tiny_scene(tmp_path):
    from sp_plugins.data import make_tiny_scene

    return make_tiny_scene(tmp_path / "sphere", mesh="sphere").root


def test_nerfbaselines_train_twice_gives_the_same_checkpoint_and_metrics(tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setenv("SP_DETERMINISTIC", "1")  # nerfstudio's torch hash encoding on two threads: the switch
    def train(out):
        return [command("nerfbaselines"), "train", "--method", "nerfacto+sp", "--backend", "python",
                "--data", tiny_scene / "blender", "--output", out, *SETTINGS]

    a, b = train_twice(train, tmp_path, threads=2)
    first, second = checkpoint(a, "checkpoint-3/nerfstudio_models/step-*.ckpt"), checkpoint(b, "checkpoint-3/nerfstudio_models/step-*.ckpt")
    assert floating(first) > 20 and differing(first, second) == []
    metrics = [json.loads((out / "results-3.json").read_text())["metrics"] for out in (a, b)]
    assert "psnr" in metrics[0] and metrics[0] == metrics[1]
