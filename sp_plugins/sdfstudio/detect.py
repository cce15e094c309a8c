"""Which ``nerfstudio`` is installed: sdfstudio's (0.1.x) or nerfstudio 1.x.

Both install a top-level package named ``nerfstudio``. We tell them apart by a file that only
sdfstudio ships (``nerfstudio/models/bakedangelo.py``), never by version, and without importing
the package (finding its spec does not run it).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

SDFSTUDIO_COMMIT = "370902a"
MARKER = Path("models") / "bakedangelo.py"
CLONE_HINT = "git clone https://github.com/autonomousvision/sdfstudio && pip install --no-deps -e ./sdfstudio"


def nerfstudio_dir() -> Path | None:
    """Directory of the installed ``nerfstudio`` package, or None when there is none."""
    spec = importlib.util.find_spec("nerfstudio")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def is_sdfstudio() -> bool:
    """True when the importable ``nerfstudio`` is sdfstudio's."""
    root = nerfstudio_dir()
    return root is not None and (root / MARKER).is_file()


def require_sdfstudio() -> None:
    """Raise ImportError with the fix when sdfstudio is not the installed ``nerfstudio``."""
    if is_sdfstudio():
        return
    root = nerfstudio_dir()
    found = f"the installed nerfstudio ({root}) is not sdfstudio" if root else "nerfstudio is not installed"
    raise ImportError(f"sp_plugins.sdfstudio needs sdfstudio, but {found}; install it: {CLONE_HINT}")
