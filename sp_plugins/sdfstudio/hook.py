"""Opt-in: sdfstudio's own, unmodified ``ns-train`` / ``ns-eval`` / ``ns-extract-mesh`` with our
patches and methods.

``python -m sp_plugins.sdfstudio.hook install`` writes one ``.pth`` file into the environment's
site-packages (``uninstall`` removes it, ``status`` tells). At interpreter start-up it loads this
file (by path: it needs only the standard library, so nothing heavy is imported at start-up) and
calls :func:`activate`, which puts a one-shot finder in front of the import system. The first
``import nerfstudio`` (or ``scripts``) then checks whether the installed ``nerfstudio`` is
sdfstudio (by a file only sdfstudio ships, ``nerfstudio/models/bakedangelo.py``, never by
version) and only then installs every compatibility patch of ``sp_plugins.patches.sdfstudio_*``
and adds our methods to ns-train's list. With nerfstudio 1.x, or without any nerfstudio, it does
nothing. ``SP_SDFSTUDIO_HOOK=0`` switches it off for one command.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import os
import sys
import sysconfig
from pathlib import Path

PTH_NAME = "sp_plugins_sdfstudio_hook.pth"
ENV_SWITCH = "SP_SDFSTUDIO_HOOK"
MARKER = ("models", "bakedangelo.py")
_HOST_TOP_LEVEL = ("nerfstudio", "scripts")


def switched_off() -> bool:
    return os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "off", "false", "no")


def installed_nerfstudio_is_sdfstudio() -> bool:
    spec = importlib.util.find_spec("nerfstudio")
    if spec is None or not spec.submodule_search_locations:
        return False
    return Path(next(iter(spec.submodule_search_locations)), *MARKER).is_file()


class _FirstImport(importlib.abc.MetaPathFinder):
    """Waits for the first import of sdfstudio's packages, then hands over to the real finder."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in _HOST_TOP_LEVEL:
            return None
        sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != _FirstImport.__name__]
        if not installed_nerfstudio_is_sdfstudio():
            return None
        from sp_plugins.patches.sdfstudio_import_hook import install_all, install_finder  # defers sdfstudio's patches

        install_all(register_methods=True, command="sdfstudio")  # opt-in: the user installed the hook
        return install_finder().find_spec(fullname, path, target)


def activate() -> None:
    """Called from the ``.pth`` file at start-up; cheap, and inert unless sdfstudio is imported."""
    # (site-packages can be processed twice, e.g. a venv's lib64 -> lib link: each run loads this
    # file as a new module, so compare by name, not by class identity)
    if switched_off() or any(type(f).__name__ == _FirstImport.__name__ for f in sys.meta_path):
        return
    if any(name in sys.modules for name in _HOST_TOP_LEVEL):
        return
    sys.meta_path.insert(0, _FirstImport())


def pth_path() -> Path:
    return Path(sysconfig.get_paths()["purelib"]) / PTH_NAME


def pth_line() -> str:
    """One start-up line; inert (no error at every start-up) once sp-plugins is uninstalled."""
    here = str(Path(__file__).resolve())
    return (
        f"import importlib.util as _u, os as _o; _p = {here!r}; "
        "_s = _o.path.isfile(_p) and _u.spec_from_file_location('_sp_plugins_sdfstudio_hook', _p); "
        "_m = _s and _u.module_from_spec(_s); _s and _s.loader.exec_module(_m); _m and _m.activate()\n"
    )


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = argv[0] if argv else "status"
    target = pth_path()
    if command == "install":
        target.write_text(pth_line())
        print(f"sp-plugins: sdfstudio hook installed ({target}); sdfstudio's ns-train now lists our methods")
    elif command == "uninstall":
        target.unlink(missing_ok=True)
        print(f"sp-plugins: sdfstudio hook removed ({target})")
    elif command == "status":
        state = "installed" if target.is_file() else "not installed"
        host = "sdfstudio" if installed_nerfstudio_is_sdfstudio() else "not sdfstudio"
        print(f"sp-plugins: sdfstudio hook {state} ({target}); installed nerfstudio: {host}")
    else:
        print(f"usage: python -m sp_plugins.sdfstudio.hook [install|uninstall|status]; got {command!r}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
