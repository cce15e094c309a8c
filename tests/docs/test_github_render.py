"""The README and every docs page read on GitHub as they do in the site.

GitHub renders Markdown as CommonMark with tables and hides HTML comments; it knows nothing of MyST. A
``:::{include}``, a ``{doc}`` role or a toctree written as a directive shows there as raw text, and what it
pulls in is missing. The pages therefore pull text in with ``<!-- site-include: ... -->`` comments that the site
expands (docs/conf.py). This test renders each page as GitHub would (markdown-it's CommonMark with tables) and
looks for MyST syntax in the text a reader sees, code blocks left out; and it checks that each relative link
of that render names a file of the checkout, as GitHub resolves it.

``SP_GITHUB_RENDER=DIR`` also writes each rendered page to DIR as HTML (the pictures of the docs' closing check).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parents[2]
PAGES = [REPO / "README.md", *sorted(p for p in (REPO / "docs").rglob("*.md") if "_build" not in p.parts)]
MYST = re.compile(r":::\{|\{doc\}|\{ref\}|\{include\}|^:(?:caption|maxdepth|hidden|start-after|end-before):|\]\([^)\s]+\)", re.M)
"""MyST's directives, roles and options, and a Markdown link left unrendered (inside an HTML block)."""


def render(text: str) -> str:
    from markdown_it import MarkdownIt

    return MarkdownIt("commonmark", {"html": True}).enable("table").render(text)


def visible(html: str) -> str:
    """The text a reader sees: code blocks, inline code and HTML comments left out, tags stripped."""
    html = re.sub(r"<pre>.*?</pre>|<code>.*?</code>|<!--.*?-->", " ", html, flags=re.S)
    return re.sub(r"<[^>]+>", " ", html)


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(REPO).as_posix() for p in PAGES])
def test_a_page_shows_no_myst_syntax_on_github(page):
    html = render(page.read_text())
    if os.environ.get("SP_GITHUB_RENDER"):
        out = Path(os.environ["SP_GITHUB_RENDER"]) / page.relative_to(REPO).with_suffix(".html")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(f"<!doctype html><meta charset=utf-8><title>{page.name}</title>"
                       "<body style='max-width:900px;margin:auto;font-family:sans-serif'>" + html)
    found = [m.group(0) for m in MYST.finditer(visible(html))]
    assert not found, f"{page.relative_to(REPO)} shows MyST syntax on GitHub: {found}"


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(REPO).as_posix() for p in PAGES])
def test_relative_links_resolve_on_github(page):
    html = render(page.read_text())
    targets = re.findall(r'(?:href|src)="([^"#:]+)(?:#[^"]*)?"', html)
    missing = sorted({t for t in targets if not (page.parent / unquote(t)).exists()})
    assert not missing, f"{page.relative_to(REPO)} links to files that do not exist: {missing}"


def test_the_checks_see_what_github_shows():
    assert MYST.search(visible(render(":::{include} ../README.md\n:::\n")))
    assert MYST.search(visible(render("Start with {doc}`getting-started`.")))
    assert MYST.search(visible(render("<!-- github-only -->*see [the README](README.md)*<!-- /github-only -->")))
    assert not MYST.search(visible(render("<!-- site-include: ../README.md#x -->\n\n```\n:::{toctree}\n```\n")))
