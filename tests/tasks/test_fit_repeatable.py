"""``sp-fit`` twice, each in a fresh process and folder, gives bit-identical checkpoints and the same
metrics (its hash grids, batches and SP noise all seeded by ``--seed``), at two torch threads."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.helpers.ns_commands import command
from tests.helpers.repeat import checkpoint, differing, floating, train_twice


@pytest.fixture
def photo(tmp_path):
    import imageio.v2 as imageio
    import skimage.data

    path = tmp_path / "astronaut.png"
    imageio.imwrite(path, skimage.data.astronaut()[::8, ::8].astype(np.uint8))
    return path


@pytest.mark.parametrize("task", ["pointcloud", "image"])
def test_sp_fit_twice_gives_the_same_checkpoint(task, photo, tmp_path):
    from sp_plugins.data.mesh import BUNDLED

    source = {"pointcloud": [BUNDLED["spot"], "--mesh-resolution", "24", "--n-points", "2000"], "image": [photo]}[task]

    def fit(out):
        return [command("sp-fit"), task, *source, "--steps", "20", "--checkpoint-every", "20", "--quiet", "--out", out]

    a, b = train_twice(fit, tmp_path, threads=2)
    first, second = checkpoint(a, "checkpoint.pt"), checkpoint(b, "checkpoint.pt")
    assert floating(first) >= 4 and differing(first, second) == []
    metrics = [json.loads((out / "metrics.json").read_text()) for out in (a, b)]
    quality = [{k: v for k, v in m.items() if not isinstance(v, float) or "second" not in k} for m in metrics]
    assert quality[0].keys() == quality[1].keys()
    for key in ("psnr", "chamfer", "fscore"):
        if key in quality[0]:
            assert quality[0][key] == quality[1][key], key
