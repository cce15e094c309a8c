"""``sp-compare`` on one pair of the sparse-view study, where SP's effect is visible.

    OMP_NUM_THREADS=1 python -m bench.sparse_compare                    # about 30 minutes on one CPU core
    OMP_NUM_THREADS=1 python -m bench.sparse_compare --seeds 0 1 2      # three pairs, about 90 minutes

The pair of ``bench/sparse_views.py`` with the clearest effect: MipNeRF (``sp-mipnerf`` with SP off) and
``sp-mipnerf`` with the sparse-view setting (alpha0 1.0, about the object's radius, to 0 at a third of
training) on the DTU-like Spot (``../shared/data/meshes/spot.ply``) from 9 of its 49 views, the
study's quick budget (``--machine.seed 0``, 2000 steps, lr 2e-3, a 4 x 128 MLP, 32 + 32 samples, 256 rays), the loss logged every
25 steps for the curves. Both are trained with nerfstudio's trainer into run folders (``bench/out/sparse_compare/``;
finished runs are kept), then ``sp-compare BASELINE SP`` writes its page, JSON and figures to ``bench/results/sparse_compare/``, and
headless Chromium opens the page offline and screenshots it there (``page.png``); ``views.png``, made smaller, is
the compare guide's figure (``docs/sp_compare_sparse.jpg``). With ``--seeds`` naming several seeds, each seed's
pair is trained (``--machine.seed N``) and ``sp-compare --baseline A0 A1 A2 --sp B0 B1 B2`` writes the report over
seeds to ``bench/results/sparse_compare/seeds/`` (each pair's report in ``seed-N/``) and ``page.png`` there (the
compare guide's ``docs/sp_compare_sparse_seeds.png``); the single-pair report above is the first seed's.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.harness import radiance as rd  # noqa: E402

OUT = ROOT / "bench" / "out" / "sparse_compare"
RESULTS = ROOT / "bench" / "results" / "sparse_compare"
DOCS_FIGURE = ROOT / "docs" / "sp_compare_sparse.jpg"
DOCS_SEEDS_FIGURE = ROOT / "docs" / "sp_compare_sparse_seeds.png"
BUDGET = rd.MipBudget(steps=2000, lr=2e-3, views=9, dtu_like=True, alpha0=1.0, end=667)
SEED = 0
LOG_EVERY = 25


def trained(sp: bool, data: Path, seed: int = SEED) -> Path:
    """The run folder's ``config.yml`` of the baseline (``sp`` False) or the SP run at ``seed``, trained if missing."""
    from sp_plugins.nerfstudio.runs import train

    name = "sp-mipnerf-1.0" if sp else "mipnerf"
    config = rd.mip_config(sp, data, BUDGET, seed, OUT if seed == SEED else OUT / f"seed{seed}", name=name)
    config.machine.seed = seed  # the weights' and rays' seed (ns-train's --machine.seed), by which sp-compare pairs runs
    config.logging.steps_per_log = LOG_EVERY  # the training curves sp-compare plots (the study's runs log none)
    path = config.get_base_dir() / "config.yml"
    done = config.get_checkpoint_dir() / f"step-{BUDGET.steps - 1:09d}.ckpt"
    if not done.is_file():
        train(config)
    assert done.is_file(), f"{done} missing after training"
    return path


def docs_figure(views: Path, out: Path) -> None:
    """The compare guide's figure: ``views.png`` at 860 px wide (JPEG: a tenth of the PNG's size)."""
    from PIL import Image

    with Image.open(views) as image:
        width, height = image.size
        image.convert("RGB").resize((860, round(height * 860 / width)), Image.LANCZOS).save(out, quality=88, optimize=True)


def screenshot(page: Path, out: Path) -> None:
    from playwright.sync_api import sync_playwright

    from tests.helpers.browser import CHROMIUM, CHROMIUM_ARGS

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        tab = browser.new_page(viewport={"width": 1280, "height": 900})
        tab.goto(page.as_uri())
        tab.screenshot(path=str(out), full_page=True)
        browser.close()


def relative(path: Path) -> str:
    """A run's path as the report names it: from the repository root, so it reads the same on any machine."""
    return str(path.relative_to(ROOT) if path.is_relative_to(ROOT) else path)


def publish(out: Path, target: Path, figure: Path) -> None:
    """An over-seeds report of ``sp-compare`` in ``out`` as the repository keeps it: screenshot its page, copy it to
    ``target`` without meshes or each pair's page (which inlines its images, 1-2 MB: its JSON and PNGs are kept),
    name files from the repository root (the true mesh's path comes from a run's config.yml, which holds the
    absolute ``--data``), and the screenshot to ``figure``."""
    screenshot(out / "compare.html", out / "page.png")
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(out, target, ignore=shutil.ignore_patterns("*.ply"))
    for page in target.glob("seed-*/compare.html"):
        page.unlink()
    for path in target.rglob("*"):
        if path.suffix in (".html", ".json", ".md"):
            path.write_text(path.read_text().replace(f"{ROOT}/", ""))
    shutil.copy(out / "page.png", figure)
    print((target / "compare.json").read_text()[:3000])


def over_seeds(pairs: list) -> None:
    """``sp-compare --baseline ... --sp ...`` over the seeds' pairs, into ``RESULTS / "seeds"``."""
    out = OUT / "compare-seeds"
    compare = Path(sys.executable).with_name("sp-compare")
    subprocess.run([str(compare), "--baseline", *(relative(b) for b, _ in pairs), "--sp", *(relative(s) for _, s in pairs),
                    "--output-dir", relative(out)], check=True, cwd=ROOT)
    publish(out, RESULTS / "seeds", DOCS_SEEDS_FIGURE)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[SEED], help="seeds to train and compare (default: 0)")
    args = parser.parse_args()
    data = rd.dtu_scene_dir("spot")
    pairs = [(trained(False, data, seed), trained(True, data, seed)) for seed in args.seeds]
    baseline, sp = pairs[0]
    RESULTS.mkdir(parents=True, exist_ok=True)
    compare = Path(sys.executable).with_name("sp-compare")
    subprocess.run([str(compare), relative(baseline), relative(sp), "--output-dir", relative(RESULTS)], check=True, cwd=ROOT)
    screenshot(RESULTS / "compare.html", RESULTS / "page.png")
    docs_figure(RESULTS / "views.png", DOCS_FIGURE)
    print((RESULTS / "compare.json").read_text()[:2000])
    if len(pairs) > 1:
        over_seeds(pairs)


if __name__ == "__main__":
    main()
