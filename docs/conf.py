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
