"""The docs site: ``docs/`` builds with Sphinx + furo + MyST with warnings as errors (broken internal
links, unknown cross-references, docstrings autodoc cannot read), every page is in a table of contents, and
the built site reads in a real browser: the index, its navigation and one guide.

The build is the command ``./run.sh docs`` runs (``python -m sphinx -W --keep-going -b html docs OUT``); the
pages' fenced blocks run in tests/test_readme.py with the README's."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.browser import CHROMIUM, CHROMIUM_ARGS, browser_or_skip

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", str(DOCS), str(out)],
                          capture_output=True, text=True, timeout=600, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert proc.returncode == 0 and "build succeeded" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert "WARNING" not in proc.stderr, proc.stderr[-6000:]
    return out


def test_every_page_is_built_and_in_the_navigation(site):
    sources = {p.relative_to(DOCS).with_suffix("").as_posix() for p in DOCS.rglob("*.md")
               if "_build" not in p.parts and p.name != "sp_defaults.md"}  # sp_defaults.md: included, not a page
    built = {p.relative_to(site).with_suffix("").as_posix() for p in site.rglob("*.html")
             if not p.relative_to(site).parts[0].startswith("_") and p.name not in ("genindex.html", "search.html", "py-modindex.html")}
    assert sources == built and len(sources) >= 18, sorted(sources ^ built)
    index = (site / "index.html").read_text()
    for page in sources - {"index"}:
        assert f'href="{page}.html"' in index, f"{page} is not in the index's navigation"


def _text(path: Path) -> str:
    """A built page's text (highlighted code is split into spans)."""
    return re.sub(r"<[^>]+>", "", path.read_text())


def test_the_included_readme_recipes_and_generated_tables_are_in_the_pages(site):
    """The README's recipes appear once in the source (the guides include them) and whole in the site; the
    generated tables (SP defaults, the method tables) are there too."""
    nerfstudio = _text(site / "guides" / "nerfstudio.html")
    assert "sp-scene spot my-scene" in nerfstudio and "ns-train neus-hashgrid" in nerfstudio
    any_method = _text(site / "guides" / "any-method.html")
    assert "nerfacto-object" in any_method and "under sp-train METHOD" in any_method
    settings = _text(site / "choosing-settings.html")
    assert "Which alpha0 for my scene" in settings and "sp-fit pointcloud" in settings  # the answer and the defaults table
    api = (site / "api.html").read_text()
    assert 'id="sp_plugins.core.config.SPConfig"' in api and 'id="sp_plugins.core.perturb.perturb"' in api


def test_the_site_reads_in_a_browser(site):
    sync_playwright = browser_or_skip()
    shots = os.environ.get("SP_DOCS_SCREENSHOTS")  # a folder: the pictures of the closing note
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto((site / "index.html").as_uri())
        assert "sp-plugins" in page.title()
        nav = page.locator(".sidebar-tree").inner_text()
        for entry in ("Getting started", "Choosing SP", "SP on any nerfstudio method", "sdfstudio", "API reference"):
            assert entry in nav, nav
        if shots:
            page.screenshot(path=str(Path(shots) / "docs_index.png"))
        page.get_by_role("link", name=re.compile("^Choosing SP")).first.click()
        page.wait_for_load_state()
        assert page.url.endswith("choosing-settings.html")
        body = page.locator("article").inner_text()
        assert "Which alpha0 for my scene" in body and re.search(r"the object.s radius", body), body[:500]
        if shots:
            page.screenshot(path=str(Path(shots) / "docs_choosing_settings.png"), full_page=False)
        page.goto((site / "guides" / "nerfstudio.html").as_uri())
        assert "ns-train sp-neus-hashgrid" in page.locator("article").inner_text()
        browser.close()
