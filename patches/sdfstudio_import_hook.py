"""Run sdfstudio's modules with our compatibility patches, without editing its files.

Targets sdfstudio commit 370902a (its ``nerfstudio`` 0.1.12 and ``scripts`` packages).

A meta-path finder in front of the others: for a module that lives in sdfstudio's install (the
``nerfstudio`` and ``scripts`` packages beside its marker file) it returns the ordinary spec with
a loader that

1. executes the module with every *around* patch active (a context manager; e.g. the tolerant
   ``dataclasses.dataclass`` of :mod:`sp_plugins.patches.sdfstudio_dataclasses`), and
2. calls the *after* patches registered for that module name on the finished module.

Modules imported before :func:`install_finder` get their *after* patches at once. No other
module's import is touched, and without sdfstudio the finder never activates.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import sys
from pathlib import Path
from types import ModuleType
from typing import Callable, ContextManager, Dict, List, Optional

from sp_plugins.sdfstudio.detect import SDFSTUDIO_COMMIT, nerfstudio_dir, require_sdfstudio

HOST_COMMIT = SDFSTUDIO_COMMIT
HOST_PACKAGES = ("nerfstudio", "scripts")
"""sdfstudio's two top-level packages (``scripts`` holds ns-train, ns-eval, ns-extract-mesh)."""

_around: List[Callable[[], ContextManager]] = []
_after: Dict[str, List[Callable[[ModuleType], None]]] = {}


def around_exec(patch: Callable[[], ContextManager]) -> None:
    """Run every later sdfstudio module's code inside ``patch()``."""
    if patch not in _around:
        _around.append(patch)


def after_exec(module_name: str, patch: Callable[[ModuleType], None]) -> None:
    """Call ``patch(module)`` once ``module_name`` has executed (now, if it already has)."""
    patches = _after.setdefault(module_name, [])
    if patch in patches:
        return
    patches.append(patch)
    module = sys.modules.get(module_name)
    if module is not None and _finished(module):
        patch(module)


def _finished(module: ModuleType) -> bool:
    spec = getattr(module, "__spec__", None)
    return not getattr(spec, "_initializing", False)


def sdfstudio_root() -> Path:
    """The directory holding sdfstudio's ``nerfstudio`` (and ``scripts``) packages."""
    require_sdfstudio()
    root = nerfstudio_dir()
    assert root is not None
    return root.parent


class _PatchingLoader(importlib.abc.Loader):
    """Wraps the ordinary loader of an sdfstudio module; everything else is delegated."""

    def __init__(self, inner) -> None:
        self._inner = inner

    def create_module(self, spec):
        return self._inner.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        with contextlib.ExitStack() as stack:
            for patch in list(_around):
                stack.enter_context(patch())
            self._inner.exec_module(module)
        for patch in _after.get(module.__name__, ()):
            patch(module)

    def __getattr__(self, name: str):  # get_source, get_filename, is_package, resource readers...
        return getattr(self._inner, name)


class SdfstudioFinder(importlib.abc.MetaPathFinder):
    """Hands sdfstudio's modules to :class:`_PatchingLoader`; ignores every other module."""

    def __init__(self, root: Path) -> None:
        self.roots = tuple(str(root / name) for name in HOST_PACKAGES)

    def find_spec(self, fullname: str, path=None, target=None):
        if fullname.partition(".")[0] not in HOST_PACKAGES:
            return None
        spec = self._spec_from_others(fullname, path, target)
        if spec is None or spec.origin is None or not spec.origin.startswith(self.roots):
            return spec
        if not isinstance(spec.loader, _PatchingLoader) and hasattr(spec.loader, "exec_module"):
            spec.loader = _PatchingLoader(spec.loader)
        return spec

    def _spec_from_others(self, fullname: str, path, target):
        for finder in sys.meta_path:
            if finder is self or isinstance(finder, SdfstudioFinder) or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                return spec
        return None


_finder: Optional[SdfstudioFinder] = None


def install_finder() -> SdfstudioFinder:
    """Put the finder first on ``sys.meta_path`` (idempotent)."""
    global _finder
    if _finder is None:
        _finder = SdfstudioFinder(sdfstudio_root())
    if _finder not in sys.meta_path:
        sys.meta_path.insert(0, _finder)
    return _finder


def install_all(register_methods: bool = False) -> None:
    """Every sdfstudio compatibility patch, plus (``register_methods``) our methods in ns-train's
    method list. Call before sdfstudio is imported; safe to call again."""
    from sp_plugins.patches import (
        sdfstudio_checkpoint_load,
        sdfstudio_cuda,
        sdfstudio_dataclasses,
        sdfstudio_lpips,
        sdfstudio_tcnn,
        sdfstudio_torch_six,
    )

    install_finder()
    sdfstudio_dataclasses.install()
    sdfstudio_torch_six.install()
    sdfstudio_lpips.install()
    sdfstudio_cuda.install()
    sdfstudio_tcnn.install()
    sdfstudio_checkpoint_load.install()
    if register_methods:
        from sp_plugins.sdfstudio.registration import add_methods

        after_exec("scripts.train", add_methods)
