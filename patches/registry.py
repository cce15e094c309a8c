"""The one place a runtime patch of a host (nerfstudio, sdfstudio, torchmetrics, Python itself) is
installed.

Each patch module defines ``PATCH``, a :class:`Patch`: the host and the version it targets, what
it changes, a ``guard`` that raises :class:`PatchGuardError` (one line naming the patch, what it
expected and what it found) when the host no longer looks as the patch was written for, and its
scope, a context manager. Nothing else installs a patch: code that needs one enters
``registry.scope(name)``, which runs the guard and then the patch's own context manager; when the
block ends the host is as it was (the tests check the identity of every patched attribute, the
warning filters, ``sys.excepthook``, ``sys.modules`` and ``dataclasses.dataclass``). Entries are
re-entrant per process: entering a patch that is already in force (a scope inside a scope of the
same patch, a model's build inside ``sp-gpu-check``'s LPIPS scope, a scope while a :func:`hold` or
:func:`install_for_process` keeps it) only counts; the guard and the patch's own context manager
run at the outermost entry, and the host is restored when the last entry ends, in whatever order
they end.

The one exception is :func:`install_for_process`: our own console commands (``sp-train``,
``sp-fit``, ``sp-sdfstudio-train`` ...) own their process, and a patch that lists the command in
``owned_commands`` may stay installed there until the process ends. The README's patch table
says which.

A new patch goes into ``patches/<host>_<what>.py`` with a ``PATCH`` and a line in :data:`ENTRIES`;
:func:`python_patch`, :func:`nerfstudio_patch` and ``sdfstudio_import_hook.sdfstudio_patch`` fill in
the host, version and owning commands of a patch of that host.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib
import importlib.metadata
import os
import sys
import threading
import weakref
from dataclasses import dataclass, field
from typing import Any, Callable, ContextManager, Dict, Iterator, List, Optional, Tuple

__all__ = [
    "ENTRIES", "OUR_COMMANDS", "SP_COMMANDS", "Patch", "PatchGuardError", "end_for_process", "entries", "get", "install_for_process",
    "nerfstudio_patch", "our_console_command", "python_patch", "scope", "host_version", "hold", "release", "in_force",
]


class PatchGuardError(RuntimeError):
    """The host changed under a patch: one line naming the patch, what it expected and found."""


def host_version(distribution: str) -> str:
    """The installed version of a distribution ("not installed" when it is not)."""
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


@dataclass(frozen=True)
class Patch:
    """One runtime patch (see the module doc)."""

    name: str
    host: str
    """The distribution (or ``python``) whose code the patch changes."""
    version: str
    """The version (or commit) it was written for."""
    changes: str
    """One line: what it replaces, with what."""
    scope_text: str
    """One line: where it is in force."""
    check: Callable[["Patch"], None]
    """Raises :class:`PatchGuardError` (through :meth:`fail`) when the host differs."""
    enter: Callable[..., ContextManager]
    """The patch itself, as a context manager (arguments are the patch's own)."""
    guarded: Tuple[Tuple[str, str], ...] = ()
    """(module, attribute) pairs the guard reads: changing any of them must make it fail."""
    owned_commands: Tuple[str, ...] = ()
    """Our console commands that keep it installed for their whole process."""
    found: Callable[[], str] = field(default=lambda: "")
    """The host version found (for the guard's message)."""
    shown: Optional[Callable[[], bool]] = None
    """Whether the host still shows the patch (for a patch whose target others replace, such as
    ``sys.excepthook``): a nested entry finding it gone enters the patch again for its own block."""

    def fail(self, expected: str, found: str) -> None:
        version = self.found() or host_version(self.host)
        raise PatchGuardError(
            f"sp_plugins patch {self.name}: written for {self.host} {self.version} ({expected}), "
            f"found {self.host} {version} with {found}; update patches/{self.name}.py"
        )

    def expect(self, condition: bool, expected: str, found: str) -> None:
        if not condition:
            self.fail(expected, found)

    def guard(self) -> None:
        self.check(self)


ENTRIES: Dict[str, str] = {
    # name -> module holding its PATCH
    "nerfstudio_external_methods": "sp_plugins.patches.nerfstudio_external_methods",
    "nerfstudio_parallel_seed": "sp_plugins.patches.nerfstudio_parallel_seed",
    "nerfstudio_sdf_field": "sp_plugins.patches.nerfstudio_sdf_field",
    "nerfstudio_marching_cubes": "sp_plugins.patches.nerfstudio_marching_cubes",
    "nerfstudio_lpips": "sp_plugins.patches.nerfstudio_lpips",
    "nerfbaselines_lpips": "sp_plugins.patches.nerfbaselines_lpips",
    "host_warnings": "sp_plugins.patches.host_warnings",
    "torch_deterministic": "sp_plugins.patches.torch_deterministic",
    "input_error_hook": "sp_plugins.patches.input_error_hook",
    "sdfstudio_import_hook": "sp_plugins.patches.sdfstudio_import_hook",
    "sdfstudio_dataclasses": "sp_plugins.patches.sdfstudio_dataclasses",
    "sdfstudio_torch_six": "sp_plugins.patches.sdfstudio_torch_six",
    "sdfstudio_cuda": "sp_plugins.patches.sdfstudio_cuda",
    "sdfstudio_lpips": "sp_plugins.patches.sdfstudio_lpips",
    "sdfstudio_tcnn": "sp_plugins.patches.sdfstudio_tcnn",
    "sdfstudio_checkpoint_load": "sp_plugins.patches.sdfstudio_checkpoint_load",
    "sdfstudio_methods": "sp_plugins.patches.sdfstudio_methods",
}

SDFSTUDIO = tuple(name for name in ENTRIES if name.startswith("sdfstudio_") and name != "sdfstudio_methods")
"""What sdfstudio at its pinned commit needs to import and run here (the import hook first);
``sdfstudio_methods`` (our methods in its ns-train) is separate."""

SP_COMMANDS: Tuple[str, ...] = (
    "sp-demo", "sp-bench", "sp-scene", "sp-fit", "sp-export-mesh", "sp-train", "sp-sweep", "sp-gpu-check", "sp-compare",
)
"""Our console commands outside sdfstudio (they own their process: the Python-level patches stay there)."""
OUR_COMMANDS: Tuple[str, ...] = SP_COMMANDS + ("sp-sdfstudio-train", "sp-sdfstudio-extract-mesh")
_MODULE_COMMANDS = {  # ``python -m <module>`` runs the same command
    "sp_plugins.cli.demo": "sp-demo", "sp_plugins.cli.bench": "sp-bench", "sp_plugins.cli.scene": "sp-scene",
    "sp_plugins.cli.fit": "sp-fit", "sp_plugins.cli.export_mesh": "sp-export-mesh", "sp_plugins.cli.sweep": "sp-sweep",
    "sp_plugins.cli.gpu_check": "sp-gpu-check", "sp_plugins.cli.train": "sp-train", "sp_plugins.cli.compare": "sp-compare",
}


@contextlib.contextmanager
def swapped(module: Any, name: str, replacement: Any) -> Iterator[None]:
    """``module.name`` is ``replacement`` within the block and what it was again after it (an ``enter``'s
    usual body: the patch is the replacement, the scope is this block)."""
    real = getattr(module, name)
    setattr(module, name, replacement)
    try:
        yield
    finally:
        setattr(module, name, real)


def python_patch(name: str, check: Callable[[Patch], None], enter: Callable[..., ContextManager],
                 guarded: Tuple[Tuple[str, str], ...], **fields: Any) -> Patch:
    """The :class:`Patch` of a change to Python itself (``sys.excepthook``, ``warnings.filters``),
    kept for the process by :data:`SP_COMMANDS`; ``fields``: ``changes``, ``scope_text``."""
    return Patch(name=name, host="python", version="3.10-3.12", check=check, enter=enter, guarded=guarded,
                 owned_commands=SP_COMMANDS, found=lambda: sys.version.split()[0], **fields)


def nerfstudio_patch(name: str, tested_versions: Tuple[str, ...], check: Callable[[Patch], None],
                     enter: Callable[..., ContextManager], guarded: Tuple[Tuple[str, str], ...], **fields: Any) -> Patch:
    """The :class:`Patch` of a change to nerfstudio, written for ``tested_versions``; ``fields``:
    ``changes``, ``scope_text`` (and ``owned_commands`` where our commands keep it)."""
    return Patch(name=name, host="nerfstudio", version=", ".join(tested_versions), check=check, enter=enter,
                 guarded=guarded, **fields)


def get(name: str) -> Patch:
    if name not in ENTRIES:
        raise KeyError(f"no patch named {name!r}; the registry has {sorted(ENTRIES)}")
    return importlib.import_module(ENTRIES[name]).PATCH


def entries(host: Optional[str] = None) -> List[Patch]:
    """Every entry (of ``host``: ``nerfstudio`` / ``sdfstudio`` / ``python`` / ``torchmetrics``)
    whose module imports here."""
    found = []
    for name in ENTRIES:
        try:
            patch = get(name)
        except ImportError:
            continue
        if host is None or patch.host == host:
            found.append(patch)
    return found


_active: Dict[str, List[Any]] = {}
"""name -> [depth, the ExitStack holding the patch's own context manager, the value it yielded]:
the entries in force in this process (through :func:`scope`, :func:`hold` or
:func:`install_for_process`)."""
_lock = threading.RLock()


def _enter(name: str, args: Tuple[Any, ...], kwargs: Dict[str, Any]) -> Tuple[Any, Optional[contextlib.ExitStack]]:
    """One more entry of ``name``: the outermost runs the guard and the patch's context manager; a
    nested one (the patch already in force in this process) only counts, and gets the outer value
    (the outermost entry's arguments decide), unless the host no longer shows the patch
    (:attr:`Patch.shown`): then it enters the patch again, on a stack of its own (returned)."""
    with _lock:
        entry = _active.get(name)
        if entry is not None:
            patch = get(name)
            own = None
            if patch.shown is not None and not patch.shown():
                patch.guard()
                own = contextlib.ExitStack()
                own.enter_context(patch.enter(*args, **kwargs))
            entry[0] += 1
            return entry[2], own
        patch = get(name)
        patch.guard()
        entry = _active.get(name)
        if entry is not None:
            # the guard entered it meanwhile: sdfstudio_import_hook's guard looks sdfstudio up, which
            # fires the opt-in import hook, which installs every sdfstudio patch, this one included
            entry[0] += 1
            return entry[2], None
        stack = contextlib.ExitStack()
        value = stack.enter_context(patch.enter(*args, **kwargs))
        _active[name] = [1, stack, value]
        return value, None


def _exit(name: str, own: Optional[contextlib.ExitStack] = None, exc_type: Any = None, exc: Any = None,
          tb: Any = None) -> bool:
    """One entry of ``name`` ends (its own stack first); the last one (in whatever order they end)
    restores the host. Returns whether the patch's context manager suppressed the exception."""
    suppressed = bool(own.__exit__(exc_type, exc, tb)) if own is not None else False
    if suppressed:
        exc_type = exc = tb = None
    with _lock:
        entry = _active[name]
        entry[0] -= 1
        if entry[0] > 0:
            return suppressed
        del _active[name]
    return bool(entry[1].__exit__(exc_type, exc, tb)) or suppressed


@contextlib.contextmanager
def scope(name: str, *args: Any, **kwargs: Any) -> Iterator[Any]:
    """Patch ``name`` for the block: its guard first, then its context manager. Re-entrant: inside
    a block (or a :func:`hold`, or :func:`install_for_process`) of the same patch it only counts,
    and the host is restored when the last of them ends."""
    value, own = _enter(name, args, kwargs)
    try:
        yield value
    except BaseException:
        if not _exit(name, own, *sys.exc_info()):
            raise
    else:
        _exit(name, own)


def in_force() -> Tuple[str, ...]:
    """The entries in force in this process now (scopes, holds and process installs)."""
    return tuple(_active)


def our_console_command() -> Optional[str]:
    """The name of our console command running this process (None when the process is not one)."""
    name = os.path.basename(sys.argv[0]) if sys.argv else ""
    if name in OUR_COMMANDS:
        return name
    argv = list(getattr(sys, "orig_argv", ()))
    if "-m" in argv[:-1]:
        return _MODULE_COMMANDS.get(argv[argv.index("-m") + 1])
    return None


_process = contextlib.ExitStack()
_installed: Dict[str, Any] = {}


def install_for_process(name: str, *args: Any, command: Optional[str] = None, **kwargs: Any) -> Any:
    """Enter ``name``'s scope until the process ends: only in our own console commands (``command``,
    else the one running), and only for a patch that lists it in ``owned_commands``. Idempotent."""
    patch = get(name)
    command = command or our_console_command()
    if command not in patch.owned_commands:
        raise RuntimeError(
            f"sp_plugins patch {name}: installed for the whole process only by our commands "
            f"{', '.join(patch.owned_commands) or '(none)'}, not by {command or 'this process'}; use registry.scope()"
        )
    global _atexit_registered
    if name not in _installed:
        if not _atexit_registered:
            atexit.register(end_for_process)  # (before the interpreter tears its modules down)
            _atexit_registered = True
        _installed[name], own = _enter(name, args, kwargs)
        _process.callback(_exit, name, own)
    return _installed[name]


_atexit_registered = False


def end_for_process() -> None:
    """End every :func:`install_for_process` entry now, as the process's exit does. For a test that
    runs one of our console commands' ``main`` inside its own process, the way a new process would
    run it: after the call the process is as it was before."""
    global _process
    stack, _process = _process, contextlib.ExitStack()
    _installed.clear()
    stack.close()


_held: Dict[str, Tuple[contextlib.ExitStack, set]] = {}


def hold(name: str, owner: Any, *args: Any, **kwargs: Any) -> bool:
    """Keep ``name``'s scope open while ``owner`` (one of our models, data managers or run configs)
    exists: entered for the first owner, left when the last one is garbage-collected (or by
    :func:`release`). A later owner enters it again if the host no longer shows it
    (:attr:`Patch.shown`). Returns True when this call entered it."""
    stack_owners = _held.get(name)
    key = id(owner)
    if stack_owners is not None:
        patch = get(name)
        if patch.shown is not None and not patch.shown():  # (dropped meanwhile, e.g. by a catch_warnings block)
            stack_owners[0].enter_context(scope(name, *args, **kwargs))
        if key not in stack_owners[1]:
            stack_owners[1].add(key)
            weakref.finalize(owner, release, name, key)
        return False
    stack = contextlib.ExitStack()
    stack.enter_context(scope(name, *args, **kwargs))
    _held[name] = (stack, {key})
    weakref.finalize(owner, release, name, key)
    return True


def release(name: str, key: Optional[int] = None) -> None:
    """``owner`` (its ``id``) no longer holds ``name``; the scope ends with the last holder (all of
    them when ``key`` is None)."""
    entry = _held.get(name)
    if entry is None:
        return
    stack, owners = entry
    owners.discard(key) if key is not None else owners.clear()
    if not owners:
        del _held[name]
        stack.close()


def held() -> Tuple[str, ...]:
    return tuple(_held)

