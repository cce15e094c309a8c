"""Pictures of the docs as a reader sees them: pages rendered as GitHub renders Markdown, and the same pages in
the built site, in headless Chromium (Debian's ``chromium``, driven by Playwright).

    python -m bench.docs_screenshots          # bench/results/docs_site/{github,site}_*.png

GitHub's render is approximated by markdown-it's CommonMark with tables and raw HTML (comments hidden), which is
what ``tests/docs/test_github_render.py`` checks every page against; the site is ``sphinx -b html docs``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench" / "results" / "docs_site"
PAGES = {  # picture name: (the page's source, its built page)
    "guides_nerfstudio": ("docs/guides/nerfstudio.md", "guides/nerfstudio.html"),
    "results": ("docs/results.md", "results.html"),
    "results_image_regime": ("docs/results/image-regime.md", "results/image-regime.html"),
}


def github_html(source: Path, out: Path) -> Path:
    from markdown_it import MarkdownIt

    html = MarkdownIt("commonmark", {"html": True}).enable("table").render(source.read_text())
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(f"<!doctype html><meta charset=utf-8><title>{source.name}</title>"
                   "<body style='max-width:900px;margin:auto;font-family:sans-serif'>" + html)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    from PIL import Image
    from playwright.sync_api import sync_playwright

    chromium = os.environ.get("SP_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
    with tempfile.TemporaryDirectory() as tmp:
        site = Path(tmp) / "site"
        subprocess.run([sys.executable, "-m", "sphinx", "-q", "-b", "html", str(REPO / "docs"), str(site)], check=True)
        args.out.mkdir(parents=True, exist_ok=True)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1100, "height": 1400})
            for name, (source, built) in PAGES.items():
                # the GitHub render sits where the page does, so its relative images resolve
                gh = github_html(REPO / source, Path(tmp) / "github" / Path(source).with_suffix(".html"))
                for kind, url in (("github", gh), ("site", site / built)):
                    shot = args.out / f"{kind}_{name}.png"
                    page.goto(url.as_uri())
                    page.screenshot(path=str(shot))
                    Image.open(shot).convert("RGB").convert("P", palette=Image.Palette.ADAPTIVE, colors=128).save(shot, optimize=True)
                    print(shot.relative_to(REPO))
            browser.close()


if __name__ == "__main__":
    main()
