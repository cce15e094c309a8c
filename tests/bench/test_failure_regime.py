"""bench/failure_regime.py end to end at a toy size: a DTU-like scene, a paired baseline/SP run, the
metrics it reports, and the one-line summary of ``--quick``."""

import dataclasses
import json
import math
import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: bench/ is not an installed package
import bench.failure_regime as fr

TINY = fr.Setting(mesh="box", steps=3, views=6, test_views=1, resolution=(24, 18), rays=32, num_samples=8,
                  num_samples_importance=4, hidden_dim=16, num_levels=4, max_res=32, log2_hashmap_size=10,
                  background_mlp=(2, 16), mesh_resolution=32, warm_up_end=1)


@pytest.fixture(scope="module")
def quick_line(tmp_path_factory):
    out = tmp_path_factory.mktemp("failure_regime")
    saved = fr.QUICK_RUN
    fr.QUICK_RUN = TINY
    try:
        line = fr.quick("box", out)
    finally:
        fr.QUICK_RUN = saved
    return line, out


def test_quick_prints_the_promised_line(quick_line):
    line, _ = quick_line
    match = re.fullmatch(r"baseline PSNR (\S+), SP PSNR (\S+), baseline failed: (yes|no), SP failed: (yes|no)", line)
    assert match, line
    base, sp = float(match[1]), float(match[2])
    assert 0 < base < 60 and 0 < sp < 60
    assert (match[3] == "yes") == (base < fr.FAILED_PSNR) and (match[4] == "yes") == (sp < fr.FAILED_PSNR)


def test_pair_result_holds_both_runs_with_their_metrics(quick_line):
    _, out = quick_line
    folder = out / "renders" / "quick-box"
    assert (folder / "test0_gt_baseline_sp.png").is_file()
    for name in fr.PAIR:
        assert (folder / f"{name}.ply").is_file() and (folder / f"{name}.npy").is_file()
    scene = next((out / "scenes").iterdir())
    info = json.loads((scene / "scene.json").read_text())
    assert info["kind"] == "dtu-like"


def test_sp_changes_the_trajectory_and_the_result_is_json(quick_line):
    """With SP on from step 0 the first losses differ (a hook that perturbed nothing would tie them)."""
    _, out = quick_line
    result = json.loads((out / "quick-box.json").read_text())
    base, sp = result[fr.PAIR[0]], result[fr.PAIR[1]]
    for m in (base, sp):
        assert math.isfinite(m["psnr"]) and math.isfinite(m["psnr_object"]) and len(m["losses"]) == TINY.steps
        assert isinstance(m["failed"], bool) and m["psnr_object"] != m["psnr"]
    assert base["losses"][0] != sp["losses"][0]


def test_cli_refuses_mesh_without_quick(capsys):
    with pytest.raises(SystemExit) as stop:
        fr.main(["box"])
    assert stop.value.code == 2 and "--quick" in capsys.readouterr().err


def test_pairs_are_paired_same_weights_and_rays(tmp_path, monkeypatch):
    """With SP switched off in both runs, the pair's losses are identical step for step: same initial
    weights and the same rays (the host's cached image order comes from Python's random, seeded too)."""
    import dataclasses

    original = fr.make_config

    def sp_off(name, *args, **kwargs):
        config = original(name, *args, **kwargs)
        config.pipeline.model.sp.enabled = False
        return config

    monkeypatch.setattr(fr, "make_config", sp_off)
    result = fr.run_pair(dataclasses.replace(TINY, steps=2, mesh_resolution=16), tmp_path, "paired")
    assert result[fr.PAIR[0]]["losses"] == result[fr.PAIR[1]]["losses"]


def test_figure_shows_renders_and_object_cropped_meshes(quick_line, tmp_path):
    """bench.failure_figure on the quick pair: the meshes are cropped to the object's box as the
    Chamfer metric crops them, and the PNG holds the three renders and three shaded meshes."""
    import imageio.v2 as imageio
    import numpy as np

    import bench.failure_figure as ff

    _, out = quick_line
    result = json.loads((out / "quick-box.json").read_text())
    scene = fr.scene_dir(fr.Setting(**{k: tuple(v) if isinstance(v, list) else v for k, v in result["setting"].items()}), out)
    c2w, K, width, height, train = ff.test_camera(scene)
    assert (width, height) == TINY.resolution and np.allclose(c2w[3], [0, 0, 0, 1])
    gt, *pair = ff.object_meshes(result, out, scene, train)
    assert len(gt.faces) and len(pair) == 2
    low, high = gt.bounds[0] - 0.2, gt.bounds[1] + 0.2  # the crop keeps faces whose centres lie within 0.1 of the object
    assert all(len(mesh.faces) for mesh in pair)  # 3 steps from the geometric-init sphere: a surface
    for mesh in pair:  # (the ground and the backdrop sphere, radius 8, are gone)
        centres = mesh.triangles_center
        assert np.all(centres >= low) and np.all(centres <= high)
    png = ff.figure(out, ["quick-box"], tmp_path / "figure.png")
    picture = imageio.imread(png)
    assert picture.ndim == 3 and picture.shape[0] > 100 and picture[..., :3].std() > 10


def test_mesh_source_finds_shared_meshes_by_stem(tmp_path):
    assert fr.mesh_source("box") == "box"
    own = tmp_path / "homer.ply"
    own.write_bytes(b"ply")
    assert fr.mesh_source(str(own)) == str(own)  # a file as given wins over the shared mesh of that stem
    if (fr.SHARED_MESHES / "homer.ply").is_file():
        assert fr.mesh_source("homer") == str(fr.SHARED_MESHES / "homer.ply")
    else:
        assert fr.mesh_source("homer") == "homer"


def test_neuralangelo_pair_runs_coarse_to_fine_against_sp(tmp_path):
    import dataclasses

    result = fr.run_pair(dataclasses.replace(TINY, method="neuralangelo", steps=2, mesh_resolution=16), tmp_path, "na")
    assert result["pair"] == list(fr.PAIRS["neuralangelo"])
    base, sp = (result[name] for name in result["pair"])
    assert len(base["losses"]) == len(sp["losses"]) == 2 and base["losses"][0] != sp["losses"][0]
    assert (tmp_path / "renders" / "na" / "test0_gt_baseline_sp.png").is_file()


def test_sdfstudio_bench_refuses_what_it_cannot_pair(capsys):
    """sdfstudio's bench has no Neuralangelo pair; grid lr and SP overrides it takes (tests/sdfstudio)."""
    import bench.sdfstudio_failure_regime as sfr

    assert sfr.unsupported(fr.SETTINGS["dtu-paper"]) == ""
    assert sfr.unsupported(fr.SETTINGS["q-lr1-wide"]) == ""
    assert "neuralangelo" in sfr.unsupported(dataclasses.replace(fr.SETTINGS["q-base"], method="neuralangelo"))
    saved = dict(fr.SETTINGS)
    fr.SETTINGS["q-na"] = dataclasses.replace(fr.SETTINGS["q-base"], method="neuralangelo")
    try:
        with pytest.raises(SystemExit) as stop:
            sfr.main(["--settings", "q-na"])
    finally:
        fr.SETTINGS.clear()
        fr.SETTINGS.update(saved)
    assert stop.value.code == 2 and "not available in sdfstudio's bench: q-na" in capsys.readouterr().err


def test_fox_setting_trains_on_the_capture_with_its_own_split(tmp_path):
    """The real capture is read where it lies by nerfstudio's instant-ngp parser (45 train / 5 test
    views); with no true mesh its geometry columns print as '-'."""
    from nerfstudio.data.dataparsers.instant_ngp_dataparser import InstantNGPDataParserConfig

    setting = fr.SETTINGS["fox-lr1"]
    assert fr.is_real(setting) and setting.grid_lr == pytest.approx(0.1)
    data = fr.data_dir(setting, fr.scene_dir(setting, tmp_path))
    assert data == fr.REAL["fox"] and (data / "transforms.json").is_file()
    config = fr.make_config("neus-hashgrid", data, setting, tmp_path, "fox")
    parser = config.pipeline.datamanager.dataparser
    assert isinstance(parser, InstantNGPDataParserConfig)
    outputs = parser.setup().get_dataparser_outputs("test")
    assert len(outputs.image_filenames) == 5
    metrics = {"psnr": 20.0, "psnr_object": 20.0, "chamfer": None, "normal_consistency": None, "median_step_s": 1.0}
    row = fr.summarise([{"tag": "fox", "setting": dataclasses.asdict(setting), "pair": list(fr.PAIR), "train_wall_s": 60,
                         fr.PAIR[0]: metrics, fr.PAIR[1]: metrics}], tmp_path).splitlines()[-1]
    assert "| - | - | - | - |" in row


def test_a_missing_capture_is_named(tmp_path, monkeypatch):
    monkeypatch.setitem(fr.REAL, "fox", tmp_path / "nowhere")
    with pytest.raises(SystemExit, match="SP_FOX_CAPTURE"):
        fr.scene_dir(fr.SETTINGS["fox-q"], tmp_path)


def test_sdfstudio_bench_holds_out_the_views_nerfstudio_holds_out():
    """The fox is tested on the same images in both hosts: nerfstudio's instant-ngp split."""
    from nerfstudio.data.utils.dataparsers_utils import get_train_eval_split_fraction

    import bench.sdfstudio_failure_regime as sfr

    for n in (7, 10, 45, 50, 51):
        assert sfr.eval_indices(n).tolist() == get_train_eval_split_fraction(list(range(n)), 0.9)[1].tolist()


def test_focus_point_is_where_the_optical_axes_meet():
    import numpy as np

    import bench.sdfstudio_failure_regime as sfr

    rng = np.random.default_rng(0)
    target = np.array([0.3, -1.2, 2.0])
    poses = []
    for _ in range(12):
        centre = target + rng.normal(size=3) * 3
        forward = (target - centre) / np.linalg.norm(target - centre)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)  # OpenCV: +z forward
        pose[:3, 3] = centre
        poses.append(pose)
    assert np.allclose(sfr.focus_point(np.array(poses)), target, atol=1e-9)
