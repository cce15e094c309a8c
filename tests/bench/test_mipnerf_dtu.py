"""bench/radiance_methods.py's MipNeRF study on the DTU-like scene (part 3) at a toy size:
the views it trains on, a far plane that reaches the backdrop, PSNR inside the object mask, SP on."""

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the checkout: bench/ is not an installed package
import bench.radiance_methods as rm  # noqa: E402
from bench.harness import radiance as rd  # noqa: E402

TOY = rd.MipBudget(steps=4, rays=32, coarse=8, fine=8, mlp_num_layers=2, mlp_layer_width=16, head_width=8, views=3,
                   alpha0=0.05, end=3, dtu_like=True)


@pytest.fixture(scope="module")
def toy_result(tmp_path_factory):
    out = tmp_path_factory.mktemp("radiance_methods")
    patch = pytest.MonkeyPatch()
    patch.setattr(rd, "OUT", out)
    real = rd.dtu_scene_dir
    patch.setattr(rd, "dtu_scene_dir", lambda scene: real(scene, views=8, test_views=2, resolution=(32, 24)))
    try:
        result = rm.mip_study("spot", TOY, seed=0, tag="toy", overwrite=False)
    finally:
        patch.undo()
    return result, out


def test_near_far_hold_the_object_and_the_backdrop_for_every_camera(toy_result):
    """Each camera's nearest object point lies beyond near and the backdrop sphere's far side inside far."""
    _, out = toy_result
    data = next((out / "scenes").iterdir()) / "blender"
    near, far = rd.dtu_near_far(data)
    info = json.loads((data.parent / "scene.json").read_text())
    for split in ("train", "test"):
        for frame in json.loads((data / f"transforms_{split}.json").read_text())["frames"]:
            centre = np.asarray(frame["transform_matrix"])[:3, 3]
            d = np.linalg.norm(centre)
            assert near < d - info["normalization"]["radius"]
            assert d + info["dtu_like"]["backdrop_radius"] <= far  # the farthest backdrop point on any ray


def test_it_trains_on_the_asked_views_with_masks_and_sp(toy_result):
    result, out = toy_result
    assert result["budget"]["dtu_like"] and result["budget"]["views"] == 3
    base, sp = result["mipnerf"], result["sp-mipnerf"]
    for m in (base, sp):
        assert len(m["psnr_object_per_view"]) == 2 and all(math.isfinite(v) for v in m["psnr_object_per_view"])
        assert m["psnr_object"] != pytest.approx(m["psnr"], abs=1e-3)  # scored on a subset, not the whole image
        assert len(m["losses"]) == TOY.steps
    assert sp["alphas"][0] == pytest.approx(TOY.alpha0) and base["alphas"][0] == 0.0
    assert sp["losses"][0] != base["losses"][0]  # same weights and rays: only SP's offsets tell them apart
    assert next((out / "mipnerf").glob("toy_*.json")).with_suffix(".png").is_file()


def test_config_reaches_the_backdrop_and_keeps_the_white_default(tmp_path):
    data = tmp_path / "blender"
    data.mkdir()
    (tmp_path / "scene.json").write_text(json.dumps({"cameras": {"distance": 4.0}, "normalization": {"radius": 0.85},
                                                     "dtu_like": {"backdrop_radius": 8.0}}))
    dtu = rd.mip_config(True, data, TOY, 0, tmp_path / "runs").pipeline.model
    white = rd.mip_config(True, data, dataclasses.replace(TOY, dtu_like=False), 0, tmp_path / "runs").pipeline.model
    assert dtu.collider_params["far_plane"] >= 12.0 and dtu.collider_params["near_plane"] < 3.15
    from sp_plugins.nerfstudio.runs import method_config

    assert white.collider_params == method_config("sp-mipnerf").pipeline.model.collider_params  # the host's 2 / 6


def test_cli_refuses_settings_that_do_not_apply_to_the_dtu_like_scene():
    proc = subprocess.run([sys.executable, "-m", "bench.radiance_methods", "mipnerf", "--dtu-like", "--image", "32"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "do not apply with --dtu-like" in proc.stderr.strip().splitlines()[-1]
