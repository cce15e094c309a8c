"""``sp-sdfstudio-train`` twice, each in a fresh process and folder, gives bit-identical checkpoints
(sp-neus-facto: its hash grid, proposal networks and SP noise), at one torch thread and at two."""

from __future__ import annotations

import pytest

from tests.helpers.repeat import checkpoint, differing, floating, train_twice
from tests.helpers.sdf_configs import BIN, train_args

CKPT = "**/sdfstudio_models/step-*.ckpt"


@pytest.mark.parametrize("threads", [1, 2])
def test_sp_sdfstudio_train_twice_gives_the_same_checkpoint(threads, sdf_scene, tmp_path):
    def train(out):
        return [BIN / "sp-sdfstudio-train", *train_args("sp-neus-facto", "neus-facto", sdf_scene, out, 3,
                                                        "--pipeline.datamanager.train-num-rays-per-batch", "128")]

    a, b = train_twice(train, tmp_path, threads=threads)
    first, second = checkpoint(a, CKPT), checkpoint(b, CKPT)
    assert floating(first) >= 20, sorted(first)
    assert differing(first, second) == []
