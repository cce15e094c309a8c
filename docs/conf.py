"""Sphinx configuration of the sp-plugins docs (Sphinx + furo + MyST, as nerfstudio, gsplat and nerfbaselines).

    ./run.sh docs        # builds docs/_build/html with warnings as errors and prints the index's path
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

project = "sp-plugins"
author = "The sp-plugins developers"
copyright = "2026, The sp-plugins developers"

def _version() -> str:
    import re

    return re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), flags=re.M)[1]


release = version = _version()

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.viewcode"]
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build", "sp_defaults.md"]  # sp_defaults.md: generated, included by choosing-settings.md
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3
html_theme = "furo"
html_title = "sp-plugins"
nitpicky = False

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
napoleon_google_docstring = True
napoleon_numpy_docstring = False


# -- pages that read on GitHub too -------------------------------------------------------------------
# GitHub shows a MyST ``{include}`` directive as raw text, so a page pulls text in with a comment GitHub hides:
#
#     <!-- site-include: ../../README.md#recipe:neus -->   the README between <!-- recipe:neus:begin / :end -->
#     <!-- site-include: sp_defaults.md offset=1 -->        a whole file, its headings one level down
#     <!-- site-include: ../CHANGELOG.md start=1 -->        a whole file from its second line
#     <!-- github-only -->[the table](sp_defaults.md)<!-- /github-only -->   what GitHub shows instead
#     <!-- toctree                                          a table of contents (its options and entries, as
#     :caption: Guides                                      MyST's toctree directive takes them), which GitHub
#     guides/own-loop                                       cannot follow; the page lists its links for GitHub
#     -->
#
# and the site replaces the first and drops the second when it reads the page (Sphinx's ``source-read``).
import os  # noqa: E402
import re  # noqa: E402

SITE_INCLUDE = re.compile(r"^<!-- site-include: (?P<path>[^#\s]+)(?:#(?P<part>\S+))?(?: offset=(?P<offset>\d))?(?: start=(?P<start>\d+))? -->$", re.M)
TOCTREE = re.compile(r"^<!-- toctree\n(.*?)^-->$", re.M | re.S)
GITHUB_ONLY = re.compile(r"<!-- github-only -->.*?<!-- /github-only -->\n?", re.S)


def included(docname: str, path: str, part: str | None, offset: int, start: int = 0) -> str:
    here = (Path(__file__).parent / docname).parent
    source = (here / path).resolve()
    text = "".join(source.read_text().splitlines(keepends=True)[start:])
    if part:
        begin, end = f"<!-- {part}:begin -->", f"<!-- {part}:end -->"
        if begin not in text or end not in text:
            raise ValueError(f"{docname}: {source.name} has no {begin} ... {end}")
        text = text.split(begin, 1)[1].split(end, 1)[0]
    if offset:
        text = re.sub(r"^(#+) ", lambda m: "#" * (len(m.group(1)) + offset) + " ", text, flags=re.M)
    # links written relative to the included file, made relative to the page that includes it
    def relink(m: re.Match) -> str:
        target = m.group(2)
        if re.match(r"[a-z]+:|#|/", target):
            return m.group(0)
        return f"{m.group(1)}({os.path.relpath(source.parent / target, here)})"
    return re.sub(r"(\]\s*)\(([^)\s]+)\)", relink, text)


def _site_includes(app, docname: str, source: list) -> None:
    text = TOCTREE.sub(lambda m: ":::{toctree}\n" + m.group(1) + ":::", GITHUB_ONLY.sub("", source[0]))
    source[0] = SITE_INCLUDE.sub(lambda m: included(docname, m["path"], m["part"], int(m["offset"] or 0), int(m["start"] or 0)), text)


def setup(app):
    app.connect("source-read", _site_includes)
