"""Run sdfstudio's modules with our compatibility patches, without editing its files (registry
entry ``sdfstudio_import_hook``; the other ``sdfstudio_*`` entries go through it).

Targets sdfstudio commit 370902a (its ``nerfstudio`` 0.1.12 and ``scripts`` packages).

A meta-path finder in front of the others: for a module that lives in sdfstudio's install (the
``nerfstudio`` and ``scripts`` packages beside its marker file) it returns the ordinary spec with
a loader that

1. executes the module with its own ``__builtins__``, whose ``__import__`` hands *that module*
   the stand-ins registered with :func:`patching` (``imports``: e.g. a ``dataclasses`` whose
   ``dataclass`` accepts sdfstudio's mutable defaults, a ``torch._six``). Every other module,
   including a third-party one that sdfstudio imports first, imports the real thing: nothing in
   ``sys.modules``, ``dataclasses`` or ``builtins`` changes;
2. calls the *after* patches registered for that module name on the finished module; they
   rebind attributes of sdfstudio's own modules only, through a ``rebind`` that remembers what
   was there.

Each patch is a context manager (:func:`patching`): leaving it unregisters it and puts back every
attribute it rebound (modules already executed keep their own builtins: they are sdfstudio's).
No other module's import is touched, and without sdfstudio the finder never activates.
"""

from __future__ import annotations

import builtins
import contextlib
import importlib.abc
import inspect
import sys
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

from sp_plugins.patches import registry
from sp_plugins.patches.registry import Patch
from sp_plugins.sdfstudio.detect import SDFSTUDIO_COMMIT, nerfstudio_dir, require_sdfstudio

HOST_COMMIT = SDFSTUDIO_COMMIT
HOST_PACKAGES = ("nerfstudio", "scripts")
"""sdfstudio's two top-level packages (``scripts`` holds ns-train, ns-eval, ns-extract-mesh)."""
SOURCE = "<sdfstudio file>"
"""In a patch's ``guarded`` pairs: (SOURCE, path) is one of sdfstudio's files the guard reads."""
SDFSTUDIO_OWNERS = ("sp-sdfstudio-train", "sp-sdfstudio-extract-mesh", "sdfstudio")
"""Who keeps the sdfstudio patches for the process: our two commands, and ``sdfstudio`` (a process
that imports sdfstudio through :func:`install_all`: the opt-in hook, a test session, a bench)."""


def sdfstudio_patch(name: str, check: Callable[[Patch], None], enter: Callable[..., Any], *sources: str,
                    guarded: Tuple[Tuple[str, str], ...] = (), **fields: Any) -> Patch:
    """The :class:`Patch` of an ``sdfstudio_*`` entry: host sdfstudio at :data:`HOST_COMMIT`, kept
    for the process by :data:`SDFSTUDIO_OWNERS`; its guard reads ``guarded`` and each of sdfstudio's
    files in ``sources`` (paths under the install, as (:data:`SOURCE`, path) pairs). ``fields``:
    ``changes``, ``scope_text`` and any other :class:`Patch` field."""
    guarded = tuple(guarded) + tuple((SOURCE, relative) for relative in sources)
    return Patch(name=name, host="sdfstudio", version=HOST_COMMIT, check=check, enter=enter, guarded=guarded,
                 owned_commands=SDFSTUDIO_OWNERS, **fields)

_MISSING = object()
_imports: Dict[str, Callable[[], ModuleType]] = {}
_after: Dict[str, List[Tuple[Callable[[ModuleType, Callable], None], Callable]]] = {}
_finder_users = 0


def _host_import(name, globals=None, locals=None, fromlist=(), level=0):
    """``__import__`` of sdfstudio's modules: a registered stand-in for ``name``, else the real import."""
    if level == 0 and name in _imports and (fromlist or "." not in name):
        return _imports[name]()
    return builtins.__import__(name, globals, locals, fromlist, level)


_host_builtins: Dict[str, Any] = {}


def host_builtins() -> Dict[str, Any]:
    """The ``__builtins__`` of sdfstudio's modules: Python's, with :func:`_host_import`."""
    if not _host_builtins:
        _host_builtins.update(vars(builtins))
        _host_builtins["__import__"] = _host_import
    return _host_builtins


@contextlib.contextmanager
def patching(
    after: Optional[Dict[str, Callable[[ModuleType, Callable], None]]] = None,
    imports: Optional[Dict[str, Callable[[], ModuleType]]] = None,
) -> Iterator[None]:
    """For the block: sdfstudio's modules import ``imports`` (name -> stand-in) from their own
    namespace, and ``after[name](module, rebind)`` runs once module ``name`` has executed (at once
    if it already has). On leaving, every attribute set through ``rebind(obj, attr, value)`` is
    put back and the patches are unregistered."""
    undo: List[Tuple[Any, str, Any]] = []

    def rebind(obj: Any, attr: str, value: Any) -> None:
        old = obj.__dict__.get(attr, _MISSING) if isinstance(obj, type) else getattr(obj, attr, _MISSING)
        undo.append((obj, attr, old))
        setattr(obj, attr, value)

    registered: List[Tuple[str, Tuple]] = []
    with finder():
        try:
            for name, stand_in in (imports or {}).items():
                _imports[name] = stand_in
            for module_name, patch in (after or {}).items():
                entry = (patch, rebind)
                _after.setdefault(module_name, []).append(entry)
                registered.append((module_name, entry))
                module = sys.modules.get(module_name)
                if module is not None and _finished(module):
                    patch(module, rebind)
            yield
        finally:
            for module_name, entry in registered:
                _after[module_name].remove(entry)
            for name, stand_in in (imports or {}).items():
                if _imports.get(name) is stand_in:
                    del _imports[name]
            for obj, attr, old in reversed(undo):
                if old is _MISSING:
                    if attr in vars(obj):
                        delattr(obj, attr)
                else:
                    setattr(obj, attr, old)


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
        module.__dict__.setdefault("__builtins__", host_builtins())
        self._inner.exec_module(module)
        for patch, rebind in list(_after.get(module.__name__, ())):
            patch(module, rebind)

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
    """Put the finder first on ``sys.meta_path`` (idempotent); :func:`finder` scopes it."""
    global _finder
    if _finder is None:
        _finder = SdfstudioFinder(sdfstudio_root())
    if _finder not in sys.meta_path:
        sys.meta_path.insert(0, _finder)
    return _finder


@contextlib.contextmanager
def finder() -> Iterator[SdfstudioFinder]:
    """The finder on ``sys.meta_path`` for the block (nested blocks share it); off after the last."""
    global _finder_users
    was_there = _finder is not None and _finder in sys.meta_path
    found = install_finder()
    _finder_users += 1
    try:
        yield found
    finally:
        _finder_users -= 1
        if _finder_users == 0 and not was_there and found in sys.meta_path:
            sys.meta_path.remove(found)


def _check(patch: Patch) -> None:
    root = nerfstudio_dir()
    patch.expect(root is not None, "sdfstudio's nerfstudio package", "no nerfstudio")
    for relative in ("nerfstudio/models/bakedangelo.py", "scripts/train.py"):
        patch.expect(bool(host_source(relative)), f"{relative} (sdfstudio's)", f"nerfstudio at {root} without it")


def host_source(relative: str) -> str:
    """The text of one of sdfstudio's files (e.g. ``scripts/train.py``), read without importing it."""
    root = nerfstudio_dir()
    if root is None:
        return ""
    path = root.parent / relative
    return path.read_text() if path.is_file() else ""


def expect_source(patch: Patch, relative: str, *snippets: str) -> None:
    """``patch``'s guard: sdfstudio's file ``relative`` still holds each snippet (what the patch fixes)."""
    text = host_source(relative)
    for snippet in snippets:
        patch.expect(snippet in text, f"{relative} containing {snippet!r}", f"{relative} without it" if text else f"no {relative}")


def expect_attribute(patch: Patch, module: ModuleType, attr: str, snippet: str = "") -> Any:
    """``patch``'s guard when it meets an executed module: the attribute it rebinds is there (and its
    source holds ``snippet``). Returns the attribute."""
    value = getattr(module, attr, None)
    patch.expect(value is not None, f"{module.__name__}.{attr}", f"no {module.__name__}.{attr}")
    if snippet:
        try:
            src = inspect.getsource(inspect.unwrap(value))
        except (OSError, TypeError):
            src = ""
        patch.expect(snippet in src, f"{module.__name__}.{attr} containing {snippet!r}", f"{module.__name__}.{attr} without it")
    return value


PATCH = sdfstudio_patch(
    "sdfstudio_import_hook", _check, finder, "nerfstudio/models/bakedangelo.py", "scripts/train.py",
    changes="sys.meta_path: a finder whose loader runs sdfstudio's modules (only) with the sdfstudio_* patches",
    scope_text="the block; process-wide (sdfstudio's modules only) in sp-sdfstudio-* and, opt-in, the .pth hook",
    found=lambda: "at " + str(nerfstudio_dir() or "none"))


def install_all(register_methods: bool = False, command: str = "sdfstudio") -> None:
    """Every sdfstudio compatibility patch for the rest of the process (our ``sp-sdfstudio-*``
    commands, the opt-in hook, and a test session or script that imports sdfstudio: at 370902a
    sdfstudio cannot be imported here without them; they change sdfstudio's modules only), plus
    (``register_methods``) our methods in ns-train's method list. Call before sdfstudio is
    imported; safe to call again."""
    for name in registry.SDFSTUDIO:
        registry.install_for_process(name, command=command)
    if register_methods:
        registry.install_for_process("sdfstudio_methods", command=command)
