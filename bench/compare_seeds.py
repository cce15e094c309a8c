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
import subprocess
import sys
from pathlib import Path

from bench.harness.common import OUT_DIR
from bench.sparse_compare import publish, relative

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "compare_seeds" / "neus"
DOCS_FIGURE = ROOT / "docs" / "sp_compare_seeds.png"


def runs(root: Path, sp: bool, seeds) -> list:
    found = []
    for seed in seeds:
        (config,) = (root / "runs" / f"as-written-{'sp' if sp else 'off'}-seed{seed}").glob("**/config.yml")
        found.append(relative(config))  # the report names files from the repository root
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--max-views", type=int, default=None, help="views rendered per run (default: all 24)")
    args = parser.parse_args()
    root = OUT_DIR / "readme_examples" / "neus"
    out = OUT_DIR / "compare_seeds" / "neus"
    compare = Path(sys.executable).with_name("sp-compare")
    extra = ["--max-views", str(args.max_views)] if args.max_views else []
    subprocess.run([str(compare), "--baseline", *runs(root, False, args.seeds), "--sp", *runs(root, True, args.seeds),
                    "--output-dir", relative(out), *extra], check=True, cwd=ROOT)
    publish(out, RESULTS, DOCS_FIGURE)


if __name__ == "__main__":
    main()
