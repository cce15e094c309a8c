"""``sp-compare`` over three seeds on the README's NeuS pair: the per-seed table, the paired difference with its
interval, the verdict, and a screenshot of its page.

The runs are ``bench.readme_examples --example neus``'s (the README's ``ns-train neus-hashgrid`` /
``ns-train sp-neus-hashgrid`` commands with ``--machine.seed 0 / 1 / 2``, 400 steps each; trained if missing)::

    OMP_NUM_THREADS=1 python -m bench.readme_examples --example neus     # the six runs (about 50 min on one core)
    OMP_NUM_THREADS=1 python -m bench.compare_seeds                       # sp-compare on them, the screenshot

Writes ``bench/results/compare_seeds/neus/`` (``compare.html``, ``compare.json``, ``seeds.png``, ``page.png``; each
pair's report in ``seed-N/``, its meshes left out) and ``docs/sp_compare_seeds.png``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

from bench.harness.common import OUT_DIR
from bench.sparse_compare import screenshot

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "compare_seeds" / "neus"
DOCS_FIGURE = ROOT / "docs" / "sp_compare_seeds.png"


def runs(root: Path, sp: bool, seeds) -> list:
    found = []
    for seed in seeds:
        (config,) = (root / "runs" / f"as-written-{'sp' if sp else 'off'}-seed{seed}").glob("**/config.yml")
        found.append(config.relative_to(ROOT) if config.is_relative_to(ROOT) else config)  # the report names files from the repository root
    return found


def relative_paths(folder: Path) -> None:
    """The reports name files from the repository root, not this machine's checkout (the true mesh's path comes
    from the run's config.yml, which holds the absolute ``--data``)."""
    for path in folder.rglob("*"):
        if path.suffix in (".html", ".json", ".md"):
            path.write_text(path.read_text().replace(f"{ROOT}/", ""))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--max-views", type=int, default=None, help="views rendered per run (default: all 24)")
    args = parser.parse_args()
    root = OUT_DIR / "readme_examples" / "neus"
    out = OUT_DIR / "compare_seeds" / "neus"
    compare = Path(sys.executable).with_name("sp-compare")
    extra = ["--max-views", str(args.max_views)] if args.max_views else []
    subprocess.run([str(compare), "--baseline", *map(str, runs(root, False, args.seeds)), "--sp",
                    *map(str, runs(root, True, args.seeds)), "--output-dir", str(out.relative_to(ROOT)), *extra], check=True, cwd=ROOT)
    screenshot(out / "compare.html", out / "page.png")
    if RESULTS.exists():
        shutil.rmtree(RESULTS)
    shutil.copytree(out, RESULTS, ignore=shutil.ignore_patterns("*.ply"))
    for page in RESULTS.glob("seed-*/compare.html"):  # each pair's page inlines its images (1-2 MB): JSON and PNGs kept
        page.unlink()
    relative_paths(RESULTS)
    shutil.copy(out / "page.png", DOCS_FIGURE)
    print((RESULTS / "compare.json").read_text()[:3000])


if __name__ == "__main__":
    main()
