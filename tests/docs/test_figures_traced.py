"""Every figure the README and the docs quote is found in the results page they cite.

A *citing block* is a table row or a paragraph of the README or of a docs page (the results pages
themselves left out) that links to a page of ``docs/results/``. Its *figures* are the decimal numbers
in it (``0.0121``, ``+4.5``, ``1,213``, ``37.63``): each must occur in one of the pages the block cites,
so a figure changed on one side only fails here. A version (``torch 2.14``) is not a figure; a setting
quoted beside a measurement is found on the page that states it.

``python -m tests.docs.test_figures_traced`` prints every block and figure it checks.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Iterator, List, Tuple

import pytest

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "docs" / "results"
LINK = re.compile(r"\]\(([^)\s]*?results/([a-z0-9-]+)\.md)(#[^)]*)?\)")
FIGURE = re.compile(r"(?<![\w.\-^/])[+\-−]?(\d{1,3}(?:,\d{3})+|\d+\.\d+)(?![\w.]*\.(?:png|jpg|md|py|json)\b)")

VERSION = re.compile(r"\b(?:torch|sp-plugins|nerfstudio|sdfstudio|nerfbaselines|Python|CUDA|Debian|version)\s+\d+(?:\.\d+)+")
"""A version number (``torch 2.14``) is not a measurement."""


def sources() -> List[Path]:
    """The README and every docs page but the results pages (which are what is cited)."""
    docs = [p for p in sorted((REPO / "docs").rglob("*.md")) if RESULTS not in p.parents and "_build" not in p.parts]
    return [REPO / "README.md", *docs]


def blocks(text: str) -> Iterator[Tuple[int, str]]:
    """(first line number, text) of each table row and each paragraph of ``text``; fenced code left out."""
    text = re.sub(r"^```.*?^```", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.M | re.S)
    para: List[str] = []
    start = 0
    for number, line in enumerate(text.split("\n"), 1):
        if line.startswith("|") or re.match(r"\s*([-*]|\d+\.) ", line):  # a row, or a list item: its own block
            if para:
                yield start, " ".join(para)
                para = []
            if not line.startswith("|"):
                start, para = number, [line]
                continue
                yield start, " ".join(para)
                para = []
            yield number, line
        elif line.strip():
            if not para:
                start = number
            para.append(line)
        elif para:
            yield start, " ".join(para)
            para = []
    if para:
        yield start, " ".join(para)


def figures(block: str) -> List[str]:
    """The decimal numbers of ``block`` outside its links' targets and inline code."""
    prose = re.sub(r"\]\([^)]*\)", "]", block)
    prose = re.sub(r"`[^`]*`", " ", prose)
    prose = re.sub(r"<!--.*?-->", " ", prose)
    prose = VERSION.sub(" ", prose)
    return [m.group(1) for m in FIGURE.finditer(prose)]


def page_numbers(slug: str) -> set:
    """Every number on a results page (thousands separators dropped)."""
    text = (RESULTS / f"{slug}.md").read_text().replace("−", "-")
    found = {m.group(1).replace(",", "") for m in FIGURE.finditer(text)}
    return found | set(re.findall(r"(?<![\d.])\d+(?![\d.])", text))  # and its whole numbers (1,213 quoted, 1213 s there)


def decimals(number: str) -> int:
    return len(number.split(".")[1]) if "." in number else 0


def on_page(figure: str, numbers: set) -> bool:
    """``figure`` is one of ``numbers``, or one of them rounded to the figure's precision (0.567 quoted as 0.57)."""
    figure = figure.replace(",", "")
    if figure in numbers:
        return True
    places, value = decimals(figure), float(figure)
    return any(decimals(n) > places and abs(round(float(n), places) - value) < 10 ** -(places + 3) for n in numbers)


def citing_blocks() -> Iterator[Tuple[str, List[str], List[str]]]:
    """(where, cited page slugs, figures) for every block that links to a results page."""
    for path in sources():
        for line, block in blocks(path.read_text()):
            cited = sorted({m.group(2) for m in LINK.finditer(block)})
            if cited:
                yield f"{path.relative_to(REPO)}:{line}", cited, figures(block)


def test_citations_name_pages_that_exist():
    missing = [(where, slug) for where, cited, _ in citing_blocks() for slug in cited
               if not (RESULTS / f"{slug}.md").exists()]
    assert not missing, missing


def test_every_quoted_figure_is_on_the_page_it_cites():
    drift = []
    checked = 0
    for where, cited, found in citing_blocks():
        numbers = set().union(*(page_numbers(s) for s in cited if (RESULTS / f"{s}.md").exists()))
        for figure in found:
            checked += 1
            if not on_page(figure, numbers):
                drift.append(f"{where}: {figure} is not on {', '.join(cited)}")
    assert checked > 100, f"only {checked} figures found: the block or number pattern no longer matches the docs"
    assert not drift, "\n".join(drift)


def test_the_figure_pattern():
    assert figures("Chamfer 0.0121 ± 0.0006, +4.5 dB [−0.08, +0.63], 1,213 s, 3 seeds, 2^13 rows") == \
        ["0.0121", "0.0006", "4.5", "0.08", "0.63", "1,213"]
    assert on_page("0.57", {"0.567"}) and on_page("1,213", {"1213"}) and on_page("30.0", {"29.98"})
    assert not on_page("0.57", {"0.5"}) and not on_page("0.57", {"0.561"}) and not on_page("30.0", {"29.94"})
    assert figures("torch 2.14, sp-plugins 0.1 and Python 3.11.7 at 0.5 s") == ["0.5"]
    assert figures("see `alpha0 0.04` and [a](results/x.md#y-1.5) or docs/a_0.5.png") == []
    assert list(blocks("| a | 1.5 |\ntext 2.5\nmore\n\n```\n3.5\n```\nlast\n- one\n  cont\n- two")) == [
        (1, "| a | 1.5 |"), (2, "text 2.5 more"), (8, "last"), (9, "- one   cont"), (11, "- two")]


@pytest.mark.parametrize("slug", sorted(p.stem for p in RESULTS.glob("*.md")))
def test_every_results_page_says_when_and_how(slug):
    """A study's page names its date and a command that remakes it, and the results index lists it."""
    text = (RESULTS / f"{slug}.md").read_text()
    assert re.search(r"20\d\d-\d\d-\d\d", text), f"{slug}: no date"
    assert re.search(r"python -m |sp-[a-z]+|ns-[a-z]+|pytest|\.ci/run|run\.sh", text), f"{slug}: no command"
    assert f"results/{slug}.md" in (REPO / "docs" / "results.md").read_text(), f"{slug}: not listed in docs/results.md"
    assert f"docs/results/{slug}.md" in (REPO / "bench" / "RESULTS.md").read_text(), f"{slug}: no row in bench/RESULTS.md"


if __name__ == "__main__":
    total = 0
    for where, cited, found in citing_blocks():
        total += len(found)
        print(f"{where} -> {', '.join(cited)}: {' '.join(found)}")
    print(f"{total} figures", file=sys.stderr)
