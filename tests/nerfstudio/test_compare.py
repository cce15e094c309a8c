"""``sp-compare RUN_A RUN_B`` (issue 56) on a baseline / SP pair trained by ``ns-train`` as a user types it: the same
held-out views rendered from both beside the truth, per-view and overall metrics equal to the model's own
evaluation, training curves with SP's alpha, both meshes against the scene's true mesh, one offline HTML page;
two runs on different data are refused in one line before anything is rendered."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import pytest

from tests.helpers.ns_commands import ENV, SDF_FLAGS, command, ns_train

PAIR = ("neus-hashgrid", "sp-neus-hashgrid")


@pytest.fixture(scope="module")
def pair(tiny_scene, ns_server, tmp_path_factory):
    """``method -> run folder`` of 11 steps of each (event files written: ``--vis viewer+tensorboard``; nerfstudio's
    default ``--logging.steps-per-log 10`` logs steps 0 and 10, two points per curve)."""
    out = {}
    for method in PAIR:
        config = ns_train(method, tmp_path_factory.mktemp(method), ["sdfstudio-data", "--data", str(tiny_scene / "sdfstudio")],
                          *SDF_FLAGS, "--vis", "viewer+tensorboard", "--machine.seed", "3",
                          *(["--pipeline.model.sp.end", "1.0"] if method.startswith("sp-") else []), steps=11, server=ns_server)
        out[method] = config.parent
    return out


def _compare(*args, expect=0):
    proc = subprocess.run([command("sp-compare"), *map(str, args)], env=ENV, capture_output=True, text=True, timeout=900)
    assert proc.returncode == expect, f"exit {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-4000:]}"
    return proc


def test_compare_renders_both_runs_scores_them_and_writes_one_offline_page(pair, tiny_scene, tmp_path):
    out = tmp_path / "compare"
    proc = _compare(pair["neus-hashgrid"], pair["sp-neus-hashgrid"], "--output-dir", out, "--mesh-resolution", "48")
    report = json.loads((out / "compare.json").read_text())
    a, b = report["runs"]
    assert "SP off" in a["label"] and "SP alpha0 0.013" in b["label"]
    n = len(report["held_out_views"])
    assert n >= 1 and len(a["views"]) == len(b["views"]) == n
    for run in (a, b):
        assert 0 < run["overall"]["psnr"] < 60 and 0 < run["overall"]["ssim"] <= 1
        assert run["overall"]["psnr"] == pytest.approx(sum(v["psnr"] for v in run["views"]) / n)
        assert run["step"] == 10 and 0 <= run["mesh"]["fscore"] <= 1 and run["mesh"]["chamfer"] > 0  # against gt_mesh.ply
    assert a["views"] != b["views"]  # two different models were rendered, not one twice
    page = (out / "compare.html").read_text()
    sources = re.findall(r'src="([^"]+)"', page)
    assert len(sources) == 2 and all(s.startswith("data:image/png;base64,") for s in sources)  # views and curves, inline
    assert (out / "views.png").is_file() and (out / "curves.png").is_file() and (out / "mesh_b.ply").is_file()
    # sdfstudio-data holds no view out (its eval split is every training image): said in the table, page and JSON
    table = proc.stdout
    assert re.search(r"^PSNR \(dB\), \d+ training views", table, flags=re.M) and "Chamfer" in table
    assert "not new views" in table and "not new views" in page and report["scored_views"] == "training views"


def test_the_fine_network_s_metrics_count_for_nerf_and_mipnerf():
    """MipNeRF's evaluation names its SSIM ``fine_ssim``: a MipNeRF pair's table had PSNR only."""
    from sp_plugins.cli.compare import image_metrics

    mip = {"psnr": 25.0, "coarse_psnr": 20.0, "fine_psnr": 25.0, "fine_ssim": 0.8, "fine_lpips": 0.1}
    assert image_metrics(mip) == {"psnr": 25.0, "ssim": 0.8, "lpips": 0.1}
    assert image_metrics({"psnr": 30.0, "ssim": 0.9, "fine_ssim": 0.1}) == {"psnr": 30.0, "ssim": 0.9}
    assert image_metrics({"psnr": 30.0, "num_rays": 5}) == {"psnr": 30.0}


def test_no_curves_figure_from_runs_that_logged_one_step(tmp_path):
    from sp_plugins.cli.compare import Run, curves_figure

    runs = [Run(name, tmp_path / "config.yml", None) for name in ("a", "b")]
    runs[0].curves = {"loss": [[0, 0.03]], "alpha": [[0, 1.0]]}
    assert not curves_figure(runs, tmp_path / "curves.png") and not (tmp_path / "curves.png").exists()
    runs[1].curves = {"loss": [[0, 0.03], [10, 0.02]]}
    assert curves_figure(runs, tmp_path / "curves.png") and (tmp_path / "curves.png").is_file()


def test_scored_views_are_named_by_what_they_are_to_training():
    from sp_plugins.cli.compare import scored_kind

    train = ["r_0.png", "r_1.png", "r_2.png"]
    assert scored_kind(train, ["t_0.png", "t_1.png"]) == "held-out views"
    assert scored_kind(train, ["r_1.png", "r_0.png"]) == "training views"
    assert scored_kind(train, ["r_1.png", "t_0.png"]) == "views (1 of them training views)"
    assert scored_kind([], ["t_0.png"]) == "held-out views"


def test_the_sp_run_s_alpha_is_read_from_its_event_file(pair, tmp_path):
    from sp_plugins.cli.compare import Run, read_curves
    from sp_plugins.cli.run_folder import load_saved_config

    curves = {}
    for method, folder in pair.items():
        run = Run(method, folder / "config.yml", load_saved_config(folder / "config.yml"))
        read_curves(run)
        curves[method] = run.curves
    assert [step for step, _ in curves["sp-neus-hashgrid"]["loss"]] == [step for step, _ in curves["neus-hashgrid"]["loss"]]
    alphas = curves["sp-neus-hashgrid"]["alpha"]
    assert [step for step, _ in alphas] == [0, 10]  # nerfstudio's default: every 10 steps
    assert alphas[0][1] == pytest.approx(0.013, rel=1e-3) and 0 <= alphas[-1][1] < alphas[0][1]  # annealed by its end
    assert all(value == 0 for _, value in curves["neus-hashgrid"].get("alpha", [[0, 0]]))


def test_two_runs_on_different_data_are_refused_in_one_line(pair, tiny_scene, tmp_path):
    other = tiny_scene.parent / "other"  # the same scene in another folder: config.yml keeps a path by its parts
    shutil.copytree(tiny_scene, other, dirs_exist_ok=True)
    moved = tmp_path / "moved-run"
    shutil.copytree(pair["sp-neus-hashgrid"], moved)
    config = moved / "config.yml"
    text = config.read_text()
    config.write_text(text.replace(f"\n      - {tiny_scene.name}\n", "\n      - other\n"))
    assert config.read_text() != text
    out = tmp_path / "compare"
    proc = _compare(pair["neus-hashgrid"], moved, "--output-dir", out, expect=2)
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("sp-compare: error: the runs were trained on different data") and str(other) in line
    assert not out.exists()


def test_a_folder_that_is_not_a_run_is_refused_in_one_line(pair, tmp_path):
    proc = _compare(pair["neus-hashgrid"], tmp_path, expect=2)
    (line,) = proc.stderr.strip().splitlines()
    assert line == f"sp-compare: error: {tmp_path}: no config.yml found in this folder; pass a run folder that ns-train " \
                   "wrote (outputs/EXPERIMENT/METHOD/TIMESTAMP) or its config.yml"


def test_the_page_opens_offline_in_a_browser_with_its_images(pair, tmp_path):
    """The report as a reader opens it: every image decoded from the page itself (no network, no files beside it)."""
    import os
    from pathlib import Path

    from tests.helpers.browser import CHROMIUM, CHROMIUM_ARGS, browser_or_skip

    sync_playwright = browser_or_skip()
    out = tmp_path / "compare"
    _compare(pair["neus-hashgrid"], pair["sp-neus-hashgrid"], "--output-dir", out, "--mesh-resolution", "32", "--max-views", "2")
    page_file = tmp_path / "alone" / "compare.html"  # moved away from its PNGs: the page must not need them
    page_file.parent.mkdir()
    shutil.move(str(out / "compare.html"), page_file)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(page_file.as_uri())
        page.wait_for_load_state()
        widths = page.eval_on_selector_all("img", "imgs => imgs.map(i => i.naturalWidth)")
        assert len(widths) == 2 and all(w > 100 for w in widths), widths
        assert "sp-neus-hashgrid" in page.locator("body").inner_text()
        if os.environ.get("SP_DOCS_SCREENSHOTS"):
            page.screenshot(path=str(Path(os.environ["SP_DOCS_SCREENSHOTS"]) / "sp_compare.png"), full_page=True)
        browser.close()
