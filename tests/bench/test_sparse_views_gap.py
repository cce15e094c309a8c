"""the regression test: on 3 views of the DTU-like Spot, MipNeRF + SP at the sparse-view
setting (alpha0 about the object's radius, to 0 at a third of training) ends above plain MipNeRF,
trained as a pair (same initial weights, same rays at every step).

Opt-in (``SP_SLOW_TESTS=1``; reported as skipped otherwise): about 13 minutes on one core. The size
is the study's own (2000 steps of 256 rays, 32 + 32 samples, a 4 x 128 MLP, 49 + 3 views of 96x72),
because it is the smallest size at which the gap showed on every seed measured (whole-image SSIM
+0.18 / +0.18 / +0.04 on seeds 0-2). Smaller sizes that fit the suite do not hold it: at 800 steps of
128 rays on 48x36 images, seed 0 gains +0.61 dB inside the object and seed 1 loses 0.79 dB; at 500
steps, or with a 4 x 64 MLP, the pair ends within 0.1 dB (``docs/results/sparse-views.md``). A test pinned to one
such seed would fail on any change to the random stream, not only when SP breaks.

Since the pair starts alike and sees the same rays, SP that no longer moves the Gaussian means (the
seam skipped, the offset dropped, alpha stuck at 0) trains the baseline again, to the same numbers,
and the margins below fail (``python tests/mutations.py --only "MipNeRF's Gaussian means not moved"``).
The seam's own tests (``tests/nerfstudio/test_seam.py``) catch that breakage in the default suite.
"""

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the checkout: bench/ is not an installed package
import bench.sparse_views as sv  # noqa: E402
from bench.harness import radiance as rd, scenes  # noqa: E402

pytestmark = pytest.mark.skipif(os.environ.get("SP_SLOW_TESTS") != "1",
                                reason="about 13 minutes on one core: SP_SLOW_TESTS=1 runs it")

GAP_BUDGET = rd.MipBudget(steps=2000, rays=256, coarse=32, fine=32, mlp_num_layers=4, mlp_layer_width=128, head_width=64,
                          views=3, dtu_like=True, lr=2e-3)
SP = sv.SPSetting.parse(sv.SPARSE)


SPOT = Path(scenes.mesh_source("spot"))
"""The study's Spot: ``../shared/data/meshes/spot.ply`` (Y-up, stood on z); the bundled ``spot`` (Z-up)
is another scene, on which these margins were never measured."""


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    if not SPOT.is_file():  # asked for (SP_SLOW_TESTS=1), so a missing mesh fails rather than skips
        pytest.fail(f"the study's mesh is not here: {SPOT} (../shared beside the checkout, or set SP_SHARED_DATA)")
    patch = pytest.MonkeyPatch()
    patch.setattr(rd, "OUT", tmp_path_factory.mktemp("gap") / "radiance_methods")
    try:
        yield sv.study("spot", GAP_BUDGET, 0, sv.run_specs([SP], freenerf=None), "gap")
    finally:
        patch.undo()


@pytest.mark.timeout(3600)
def test_sp_at_the_sparse_view_setting_ends_above_mipnerf_on_three_views(pair):
    base, sp = pair[sv.BASELINE], pair[SP.name]
    assert base["init_weights"] == sp["init_weights"]  # paired: one start
    assert base["alphas"][0] == 0.0 and sp["alphas"][0] == pytest.approx(1.0)
    assert sp["alphas"][-1] == 0.0  # SP over before the end: what is scored is an ordinary field
    # the study's seed 0: object 11.57 -> 13.58 dB, whole-image SSIM 0.141 -> 0.321
    assert sp["ssim"] > base["ssim"] + 0.1, (base["ssim"], sp["ssim"])
    assert sp["psnr_object"] > base["psnr_object"] + 1.0, (base["psnr_object"], sp["psnr_object"])
