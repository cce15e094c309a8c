"""``sp-compare RUN_A RUN_B`` on a baseline / SP pair trained by ``ns-train`` as a user types it: the same
held-out views rendered from both beside the truth, per-view and overall metrics equal to the model's own
evaluation, training curves with SP's alpha, both meshes against the scene's true mesh, one offline HTML page;
two runs on different data are refused in one line before anything is rendered."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import pytest

from tests.helpers.errors import refused
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


def _compare(*args, expect=0, server=None):
    """``sp-compare ARGS`` as typed: a child forked from the session's fork server (nerfstudio imported once) when
    ``server`` is given, else a new interpreter (the refusals below run the real script so)."""
    if server is not None:
        return server.call([command("sp-compare"), *args], expect=expect)
    proc = subprocess.run([command("sp-compare"), *map(str, args)], env=ENV, capture_output=True, text=True, timeout=900)
    assert proc.returncode == expect, f"exit {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-4000:]}"
    return proc


def test_compare_renders_both_runs_scores_them_and_writes_one_offline_page(pair, tiny_scene, tmp_path, ns_server):
    out = tmp_path / "compare"
    proc = _compare(pair["neus-hashgrid"], pair["sp-neus-hashgrid"], "--output-dir", out, "--mesh-resolution", "48", server=ns_server)
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
    # one pair: it says it cannot tell SP from run-to-run noise, and how large that noise was
    from sp_plugins.cli.compare import ONE_PAIR_NOTE

    assert ONE_PAIR_NOTE in proc.stdout and report["noise"] == ONE_PAIR_NOTE
    assert "1.6-2.3 dB" in ONE_PAIR_NOTE and "0.0006" in ONE_PAIR_NOTE and "--baseline A1 A2 A3 --sp B1 B2 B3" in ONE_PAIR_NOTE


def test_the_fine_network_s_metrics_count_for_nerf_and_mipnerf():
    """MipNeRF's evaluation names its SSIM ``fine_ssim``: a MipNeRF pair's table had PSNR only."""
    from sp_plugins.cli.compare import image_metrics

    mip = {"psnr": 25.0, "coarse_psnr": 20.0, "fine_psnr": 25.0, "fine_ssim": 0.8, "fine_lpips": 0.1}
    assert image_metrics(mip) == {"psnr": 25.0, "ssim": 0.8, "lpips": 0.1}
    assert image_metrics({"psnr": 30.0, "ssim": 0.9, "fine_ssim": 0.1}) == {"psnr": 30.0, "ssim": 0.9}
    assert image_metrics({"psnr": 30.0, "num_rays": 5}) == {"psnr": 30.0}


def test_no_curves_figure_from_runs_that_logged_one_step(tmp_path):
    from sp_plugins.cli.compare_report import Run, curves_figure

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


def test_two_runs_on_different_data_are_refused_in_one_line(pair, tiny_scene, tmp_path, ns_server):
    other = tiny_scene.parent / "other"  # the same scene in another folder: config.yml keeps a path by its parts
    shutil.copytree(tiny_scene, other, dirs_exist_ok=True)
    moved = tmp_path / "moved-run"
    shutil.copytree(pair["sp-neus-hashgrid"], moved)
    config = moved / "config.yml"
    text = config.read_text()
    config.write_text(text.replace(f"\n      - {tiny_scene.name}\n", "\n      - other\n"))
    assert config.read_text() != text
    out = tmp_path / "compare"
    proc = _compare(pair["neus-hashgrid"], moved, "--output-dir", out, expect=2, server=ns_server)
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("sp-compare: error: the runs were trained on different data") and str(other) in line
    assert not out.exists()


def test_a_folder_that_is_not_a_run_is_refused_in_one_line(pair, tmp_path):
    proc = _compare(pair["neus-hashgrid"], tmp_path, expect=2)
    (line,) = proc.stderr.strip().splitlines()
    assert line == f"sp-compare: error: {tmp_path}: no config.yml found in this folder; pass a run folder that ns-train " \
                   "wrote (outputs/EXPERIMENT/METHOD/TIMESTAMP) or its config.yml"


def test_the_page_opens_offline_in_a_browser_with_its_images(pair, tmp_path, ns_server):
    """The report as a reader opens it: every image decoded from the page itself (no network, no files beside it)."""
    import os
    from pathlib import Path

    from tests.helpers.browser import CHROMIUM, CHROMIUM_ARGS, browser_or_skip

    sync_playwright = browser_or_skip()
    out = tmp_path / "compare"
    _compare(pair["neus-hashgrid"], pair["sp-neus-hashgrid"], "--output-dir", out, "--mesh-resolution", "32", "--max-views", "2", server=ns_server)
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


# -- over seeds ------------------------------------------------------------------------------------
def _payload(seed, a, b, kind="held-out views"):
    """A pair's compare.json content with overall and mesh metrics ``a`` / ``b`` (dicts)."""
    def run(label, m):
        return {"label": label, "overall": {k: v for k, v in m.items() if k in ("psnr", "ssim", "lpips")},
                "mesh": {k: v for k, v in m.items() if k in ("chamfer", "fscore", "normal_consistency")} or None}
    return seed, {"runs": [run("baseline", a), run("SP", b)], "scored_views": kind}


def test_the_seed_summary_is_each_side_s_spread_and_the_paired_difference_with_its_t_interval():
    from scipy.stats import t

    from sp_plugins.cli.compare_report import per_seed_table, seed_summary, summary_table

    pairs = [_payload(0, {"psnr": 20.0, "chamfer": 0.010}, {"psnr": 21.0, "chamfer": 0.012}),
             _payload(1, {"psnr": 22.0, "chamfer": 0.011}, {"psnr": 23.2, "chamfer": 0.013}),
             _payload(2, {"psnr": 21.0, "chamfer": 0.012}, {"psnr": 21.8, "chamfer": 0.011})]
    psnr, chamfer = seed_summary(pairs)
    assert psnr["metric"] == "psnr" and psnr["seeds"] == [0, 1, 2]
    assert psnr["baseline"] == [20.0, 22.0, 21.0] and psnr["sp"] == [21.0, 23.2, 21.8]
    assert psnr["baseline_mean"] == pytest.approx(21.0) and psnr["baseline_sd"] == pytest.approx(1.0)
    assert psnr["sp_mean"] == pytest.approx(22.0) and psnr["sp_sd"] == pytest.approx(1.24**0.5)
    d = psnr["difference"]  # differences 1.0, 1.2, 0.8: mean 1.0, sd 0.2
    half = t.ppf(0.975, 2) * 0.2 / 3**0.5
    assert d["n"] == 3 and d["mean"] == pytest.approx(1.0) and d["sd"] == pytest.approx(0.2)
    assert (d["low"], d["high"]) == (pytest.approx(1.0 - half), pytest.approx(1.0 + half)) and d["verdict"] == "better"
    # Chamfer: lower is better; differences +0.002, +0.002, -0.001 -> the interval holds 0
    assert chamfer["higher_is_better"] is False and chamfer["difference"]["verdict"] == "within the noise"
    rows = summary_table([psnr, chamfer], "held-out views")
    assert rows[0] == ["", "baseline (3 seeds)", "SP (3 seeds)", "SP - baseline [95% t interval]", "verdict for SP"]
    assert rows[1] == ["PSNR (dB), held-out views", "21 ± 1", "22 ± 1.1", f"+1 [{1 - half:+.3g}, {1 + half:+.3g}]", "better"]
    assert rows[2][0] == "Chamfer (of the true diagonal)" and rows[2][4] == "within the noise"
    assert per_seed_table([psnr, chamfer])[1:] == [["0", "20 -> 21", "0.01 -> 0.012"], ["1", "22 -> 23.2", "0.011 -> 0.013"],
                                                   ["2", "21 -> 21.8", "0.012 -> 0.011"]]


def test_a_lower_is_better_metric_that_falls_everywhere_is_better_and_a_missing_metric_is_left_out():
    from sp_plugins.cli.compare_report import seed_summary

    pairs = [_payload(s, {"psnr": 20.0, "lpips": 0.30 + s / 100}, {"psnr": 20.0 + s / 10, "lpips": 0.20 + s / 90}) for s in range(3)]
    pairs.append(_payload(3, {"psnr": 20.0, "lpips": 0.31}, {"psnr": 20.4, "lpips": 0.215}))
    lpips = next(item for item in seed_summary(pairs) if item["metric"] == "lpips")
    assert lpips["difference"]["verdict"] == "better" and lpips["difference"]["high"] < 0
    assert [item["metric"] for item in seed_summary(pairs)] == ["psnr", "lpips"]  # no SSIM, no mesh: no rows
    worse = [_payload(s, {"psnr": 25.0 + s}, {"psnr": 24.0 + s - s / 10}) for s in range(3)]
    assert seed_summary(worse)[0]["difference"]["verdict"] == "worse"
    one = seed_summary([_payload(0, {"psnr": 20.0}, {"psnr": 25.0})])[0]["difference"]
    assert one["verdict"] == "one pair: cannot tell" and one["low"] is None


def test_the_pair_table_is_b_minus_a_for_each_metric_both_runs_have():
    from pathlib import Path

    from sp_plugins.cli.compare_report import Run, table

    a, b = Run("A", Path("a"), None), Run("B", Path("b"), None)
    a.overall, b.overall = {"psnr": 20.0, "ssim": 0.5}, {"psnr": 21.25, "ssim": 0.45, "lpips": 0.2}
    a.views, b.views = [{}] * 3, [{}] * 3
    a.mesh, b.mesh = {"chamfer": 0.02, "fscore": 0.5}, {"chamfer": 0.015, "fscore": 0.75}
    a.step, b.step = 99, 100
    assert table([a, b], "training views") == [
        ["", "A", "B", "B - A"],
        ["PSNR (dB), 3 training views", "20", "21.25", "+1.25"],
        ["SSIM, 3 training views", "0.5", "0.45", "-0.05"],
        ["Chamfer (of the true diagonal)", "0.02", "0.015", "-0.005"],
        ["F-score @1%", "0.5", "0.75", "+0.25"],
        ["trained steps", "99", "100", ""],
    ]


@pytest.fixture(scope="module")
def second_seed(tiny_scene, ns_server, tmp_path_factory):
    """The pair again at seed 4 (the module's pair is seed 3)."""
    out = {}
    for method in PAIR:
        config = ns_train(method, tmp_path_factory.mktemp(f"{method}-4"), ["sdfstudio-data", "--data", str(tiny_scene / "sdfstudio")],
                          *SDF_FLAGS, "--vis", "viewer+tensorboard", "--machine.seed", "4",
                          *(["--pipeline.model.sp.end", "1.0"] if method.startswith("sp-") else []), steps=3, server=ns_server)
        out[method] = config.parent
    return out


def test_runs_over_seeds_are_paired_by_seed_and_summarised_from_each_pair_s_own_report(pair, second_seed, tmp_path, ns_server):
    out = tmp_path / "seeds"
    # given in different orders on the two sides: the pairing is by --machine.seed, not by position
    proc = _compare("--baseline", pair["neus-hashgrid"], second_seed["neus-hashgrid"], "--sp", second_seed["sp-neus-hashgrid"],
                    pair["sp-neus-hashgrid"], "--output-dir", out, "--max-views", "1", "--mesh-resolution", "32", server=ns_server)
    report = json.loads((out / "compare.json").read_text())
    assert report["seeds"] == [3, 4] and report["interval"].startswith("95% Student t")
    for seed, steps in ((3, 10), (4, 2)):
        pair_report = json.loads((out / f"seed-{seed}" / "compare.json").read_text())
        base, sp = pair_report["runs"]
        assert (base["seed"], sp["seed"]) == (seed, seed) and "SP off" in base["sp"] and "SP alpha0" in sp["sp"]
        assert base["step"] == sp["step"] == steps
        assert len(base["views"]) == len(sp["views"]) == 1  # --max-views 1
        i = report["seeds"].index(seed)
        for item in report["summary"]:
            where = "overall" if item["metric"] in ("psnr", "ssim", "lpips") else "mesh"
            assert item["baseline"][i] == base[where][item["metric"]] and item["sp"][i] == sp[where][item["metric"]]
    psnr = next(item for item in report["summary"] if item["metric"] == "psnr")
    diffs = [b - a for a, b in zip(psnr["baseline"], psnr["sp"])]
    assert psnr["difference"]["mean"] == pytest.approx(sum(diffs) / 2) and psnr["difference"]["n"] == 2
    assert report["table"][1][0] == "PSNR (dB), training views" and psnr["difference"]["verdict"] in proc.stdout
    page = (out / "compare.html").read_text()
    assert 'href="seed-3/compare.html"' in page and 'href="seed-4/compare.html"' in page and (out / "seeds.png").is_file()


@pytest.mark.parametrize("args, message", [
    (["--baseline", "A"], "--sp is missing"),
    (["--baseline", "A", "B", "--sp", "C"], "--baseline has 2 runs and --sp 1"),
    (["X", "Y", "--baseline", "A", "--sp", "B"], "either RUN_A RUN_B or --baseline"),
    (["X"], "pass two runs"),
])
def test_malformed_seed_options_are_refused_in_one_line(args, message, tmp_path):
    proc = _compare(*args, "--output-dir", tmp_path / "x", expect=2)
    line = refused(proc, "sp-compare")
    assert line.startswith("sp-compare: error: ") and message in line


def test_two_runs_of_one_seed_on_a_side_or_unmatched_seeds_are_refused(pair, second_seed, tmp_path, ns_server):
    proc = _compare("--baseline", pair["neus-hashgrid"], pair["neus-hashgrid"], "--sp", pair["sp-neus-hashgrid"],
                    second_seed["sp-neus-hashgrid"], "--output-dir", tmp_path / "x", expect=2, server=ns_server)
    assert "--baseline has two runs of seed 3" in refused(proc, "sp-compare")
    proc = _compare("--baseline", pair["neus-hashgrid"], "--sp", second_seed["sp-neus-hashgrid"], "--output-dir", tmp_path / "y",
                    expect=2, server=ns_server)
    assert "different seeds (baseline [3], SP [4])" in refused(proc, "sp-compare")
