"""Issue 31's regression test: on 3 views of the DTU-like Spot, MipNeRF + SP at the sparse-view
setting (alpha0 about the object's radius, to 0 at a third of training) ends above plain MipNeRF,
trained as a pair (same initial weights, same rays at every step).

The size is the smallest the screen found where the gap still shows (``bench/RESULTS.md``, "Sparse
views against FreeNeRF-lite"): 800 steps of 64 rays, 32 + 32 samples, the study's 4 x 128 MLP,
49 + 3 views of 48x36 (the study: 2000 steps, 256 rays, 96x72). At 500 steps, or with a 4 x 64 MLP,
the two runs end within 0.1 dB of each other. Since the pair starts alike and sees the same rays,
SP that no longer moves the Gaussian means (the seam skipped, the offset dropped, alpha stuck at 0)
trains the baseline again, to the same numbers, and the margins below fail.
"""

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the checkout: bench/ is not an installed package
import bench.sparse_views as sv  # noqa: E402
from bench.harness import radiance as rd  # noqa: E402

GAP_BUDGET = rd.MipBudget(steps=800, rays=64, coarse=32, fine=32, mlp_num_layers=4, mlp_layer_width=128, head_width=64,
                          views=3, dtu_like=True, lr=2e-3)
RESOLUTION = (48, 36)
SP = sv.SPSetting.parse(sv.SPARSE)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("gap") / "radiance_methods"
    patch = pytest.MonkeyPatch()
    patch.setattr(rd, "OUT", out)
    real = rd.dtu_scene_dir
    patch.setattr(rd, "dtu_scene_dir", lambda scene, up_axis=None: real(scene, up_axis, views=49, test_views=3, resolution=RESOLUTION))
    try:
        yield sv.study("spot", GAP_BUDGET, 0, sv.run_specs([SP], freenerf=None), "gap")
    finally:
        patch.undo()


@pytest.mark.timeout(900)
def test_sp_at_the_sparse_view_setting_ends_above_mipnerf_on_three_views(pair):
    base, sp = pair[sv.BASELINE], pair[SP.name]
    assert base["init_weights"] == sp["init_weights"]  # paired: one start
    assert base["alphas"][0] == 0.0 and sp["alphas"][0] == pytest.approx(1.0)
    assert sp["alphas"][-1] == 0.0  # SP over before the end: what is scored is an ordinary field
    # measured here: object 11.63 -> 12.12 dB, whole image 15.90 -> 16.14 dB
    assert sp["psnr_object"] > base["psnr_object"] + 0.25, (base["psnr_object"], sp["psnr_object"])
    assert sp["psnr"] > base["psnr"] + 0.1, (base["psnr"], sp["psnr"])
