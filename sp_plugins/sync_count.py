"""Count the operators that would stall a CUDA stream, per call site, on any device.

A GPU training step should queue work and never wait for it; every read of a device value by the
host (``.item()``, ``bool(t)``, ``float(t)``, ``.tolist()``, ``.numpy()``), every op whose output
size depends on the data (``nonzero``, ``unique``, boolean-mask indexing, ``masked_select``) blocks
the CPU until the GPU has caught up. Those ops are the same on the CPU, so counting them there (a
``TorchDispatchMode``, as a GPU profiler would see them) finds a GPU run's stalls without a GPU.

API::

    from sp_plugins.sync_count import count_syncs, SyncCounter, ours

    counts = count_syncs(trainer.step)          # {"sp_plugins/tasks/image.py:358": 1, ...}
    assert not ours(counts), ours(counts)       # sites inside this package only

    with SyncCounter() as counter:              # or around several calls
        for _ in range(3):
            trainer.step()
    counter.counts                              # {"path:line": n}, all sites
    counter.ops                                 # {"path:line": {"aten._local_scalar_dense": n, ...}}
    counter.ours()                              # the sites inside sp_plugins (and patches)
    counter.report()                            # one line per site, most frequent first
    SyncCounter(devices={"cuda"})               # on a GPU run: only ops on CUDA tensors (a CPU
                                                # scalar's .item() does not stall the stream)
    SyncCounter(skip_files=[__file__])          # a driver inside sp_plugins (sp-gpu-check) that calls
                                                # the host's trainer: its frames are no site
    site_of("/abs/path/file.py", 12)            # ("sp_plugins/...:12", True): a warning's frame as a
                                                # site (torch.cuda.set_sync_debug_mode's warnings)

A site is ``path:line`` of the innermost frame outside torch, the line that asked for the value:
ours when it lies inside ``sp_plugins`` (its ``patches`` included; the path
from the package's parent, ``sp_plugins/tasks/image.py:358``), the host's otherwise, also when our
mixin called the host's method that syncs (path relative to its ``sys.path`` entry:
``nerfstudio/model_components/ray_samplers.py:120``).

What is counted: ``aten._local_scalar_dense`` (behind ``.item()``, ``bool()``, ``float()``,
``int()``, formatting), ``nonzero`` / ``argwhere``, every ``unique`` variant, ``masked_select``,
``index`` / ``index_put`` with a boolean index, ``equal``, ``bincount`` and ``repeat_interleave``
without an output size; and, through Python wrappers (on a CPU they reach no operator),
``Tensor.tolist``, ``Tensor.numpy`` (so ``np.asarray(t)``), ``Tensor.cpu`` and ``.to("cpu")`` of a
tensor not on the CPU. Not counted: reads of CPU scalars that stay on the CPU in a GPU run too
(torch's optimizers read their step counters from ``torch/optim``); ops on the ``meta`` device.
A CPU count cannot see a branch that only a GPU takes; code that picks a cheaper CPU-only path
(one that syncs) shows it here and should be judged with that in mind.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections import Counter, defaultdict
from typing import Any, Callable, Dict, Iterator, Optional

import torch
from torch.utils._python_dispatch import TorchDispatchMode

__all__ = ["SyncCounter", "count_syncs", "ours", "SYNC_OPS"]

_aten = torch.ops.aten
SYNC_OPS = frozenset(
    getattr(_aten, name)
    for name in (
        "_local_scalar_dense", "nonzero", "argwhere", "unique", "_unique", "_unique2", "unique_dim",
        "unique_consecutive", "unique_dim_consecutive", "masked_select", "equal", "bincount", "is_nonzero",
    )
    if hasattr(_aten, name)
)
"""Ops that always wait for the device (a value or a data-dependent size back on the host)."""

_INDEX_OPS = frozenset(getattr(_aten, n) for n in ("index", "index_put", "index_put_", "_index_put_impl_") if hasattr(_aten, n))
_TORCH_DIR = os.path.dirname(os.path.abspath(torch.__file__)) + os.sep
_THIS_FILE = os.path.abspath(__file__)
_CPU_BY_DESIGN = (os.path.join(_TORCH_DIR, "optim") + os.sep,)  # step counters: CPU tensors in a GPU run too
_WRAPPERS = tuple(os.path.join(_TORCH_DIR, *p.split("/")) for p in (
    "_tensor.py", "overrides.py", "_compile.py", "_dynamo/", "utils/_python_dispatch.py", "utils/_contextlib.py"))
"""torch's Python shims between a caller and the op (``Tensor.__format__`` -> ``item``, decorators):
skipped when finding the frame that made the call."""


def _our_roots() -> tuple[str, ...]:
    """Folders whose files are ours: the package, and the mapped patches."""
    import importlib.util

    roots = [os.path.dirname(os.path.abspath(__file__))]
    for name in ("sp_plugins.patches",):
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        for path in (spec.submodule_search_locations or []) if spec else []:
            roots.append(os.path.abspath(path))
    return tuple(dict.fromkeys(r.rstrip(os.sep) + os.sep for r in roots))


def _display(path: str, roots: tuple[str, ...]) -> str:
    """``sp_plugins/...`` for ours (patches under its package name), else the
    path relative to its longest ``sys.path`` entry."""
    package = roots[0]
    if path.startswith(package):
        return "sp_plugins/" + path[len(package):].replace(os.sep, "/")
    for root, name in zip(roots[1:], ("patches",)):
        if path.startswith(root):
            return f"sp_plugins/{os.path.basename(root.rstrip(os.sep)) or name}/" + path[len(root):].replace(os.sep, "/")
    best = max((p for p in map(os.path.abspath, filter(None, sys.path)) if path.startswith(p + os.sep)), key=len, default=None)
    return os.path.relpath(path, best).replace(os.sep, "/") if best else path


def _is_bool_index(indices: Any) -> bool:
    return isinstance(indices, (list, tuple)) and any(
        isinstance(t, torch.Tensor) and t.dtype in (torch.bool, torch.uint8) for t in indices
    )


def _on(devices: Optional[frozenset], args, kwargs) -> bool:
    """Whether an op touches a tensor on one of ``devices`` (None: any device but meta)."""
    tensors = [a for a in (*args, *kwargs.values()) if isinstance(a, torch.Tensor)]
    tensors += [t for a in args if isinstance(a, (list, tuple)) for t in a if isinstance(t, torch.Tensor)]
    if devices is None:
        return not tensors or any(t.device.type != "meta" for t in tensors)
    return any(t.device.type in devices for t in tensors)


def _syncs(func, args, kwargs) -> bool:
    packet = getattr(func, "overloadpacket", func)
    if packet in SYNC_OPS:
        return True
    if packet in _INDEX_OPS:
        return len(args) > 1 and _is_bool_index(args[1])
    if packet is _aten.repeat_interleave:  # the Tensor overload (the others decompose into it)
        return func is _aten.repeat_interleave.Tensor and kwargs.get("output_size") is None
    return False


class SyncCounter(TorchDispatchMode):
    """Counts stalling ops per call site while active (a context manager; nestable with other
    modes). ``counts`` / ``ops`` are filled as ops run; see the module docstring."""

    def __init__(self, devices: Optional[Any] = None, skip_files: Any = ()) -> None:
        super().__init__()
        self.devices = frozenset(devices) if devices is not None else None
        self._skip = frozenset(os.path.abspath(f) for f in skip_files) | {_THIS_FILE}
        self.counts: Counter = Counter()
        self.ops: Dict[str, Counter] = defaultdict(Counter)
        self._roots = _our_roots()
        self._ours: set[str] = set()
        self._patches: Optional[contextlib.ExitStack] = None

    # -- recording ------------------------------------------------------------------------------
    def _site(self) -> Optional[str]:
        """The innermost frame outside torch (the line that asked for the value: ours when it is in
        sp_plugins, the host's when the host's code called, even from a method of our mixins); None
        for a read torch makes of its own CPU-by-design scalars (the innermost real frame is in
        ``torch/optim``)."""
        frame = sys._getframe(1)
        innermost = True
        while frame is not None:
            path = os.path.abspath(frame.f_code.co_filename)
            frame, lineno = frame.f_back, frame.f_lineno
            if path in self._skip or path.startswith(_WRAPPERS):
                continue
            if innermost and path.startswith(_CPU_BY_DESIGN):
                return None
            innermost = False
            if path.startswith(_TORCH_DIR):
                continue
            site = f"{_display(path, self._roots)}:{lineno}"
            if path.startswith(self._roots):
                self._ours.add(site)
            return site
        return "<unknown>"

    def record(self, name: str) -> None:
        site = self._site()
        if site is not None:
            self.counts[site] += 1
            self.ops[site][name] += 1

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if _syncs(func, args, kwargs) and _on(self.devices, args, kwargs):
            self.record(f"aten.{func.overloadpacket.__name__}")
        return func(*args, **kwargs)

    # -- host reads that reach no operator on a CPU ------------------------------------------------
    def __enter__(self) -> "SyncCounter":
        self._patches = contextlib.ExitStack()
        counter = self

        def wrap(name: str, when: Callable[..., bool]):
            original = getattr(torch.Tensor, name)

            def reader(self, *args, **kwargs):
                if when(self, *args, **kwargs) and _on(counter.devices, (self,), {}):
                    counter.record(f"Tensor.{name}")
                return original(self, *args, **kwargs)

            setattr(torch.Tensor, name, reader)
            self._patches.callback(setattr, torch.Tensor, name, original)

        def to_host(t, *args, **kwargs):
            try:
                device = torch._C._nn._parse_to(*args, **kwargs)[0]
            except (TypeError, RuntimeError):
                return False
            return device is not None and device.type == "cpu" and t.device.type != "cpu"

        always = lambda t, *a, **k: True  # noqa: E731
        wrap("tolist", always)
        wrap("numpy", always)
        wrap("cpu", lambda t, *a, **k: t.device.type != "cpu")
        wrap("to", to_host)
        try:
            return super().__enter__()
        except BaseException:
            self._patches.close()
            raise

    def __exit__(self, *exc) -> None:
        try:
            super().__exit__(*exc)
        finally:
            if self._patches is not None:
                self._patches.close()
                self._patches = None

    # -- reading ----------------------------------------------------------------------------------
    def ours(self) -> Dict[str, int]:
        """The sites inside this package, ``{"sp_plugins/...:line": n}``."""
        return {site: n for site, n in self.counts.items() if site in self._ours}

    def report(self, only_ours: bool = False) -> str:
        """One line per site, ``n  path:line  (op x n, ...)``, most frequent first."""
        rows = self.ours() if only_ours else self.counts
        return "\n".join(
            f"{n:5d}  {site}  ({', '.join(f'{op} x{k}' for op, k in self.ops[site].most_common())})"
            for site, n in sorted(rows.items(), key=lambda kv: (-kv[1], kv[0]))
        )


def site_of(filename: str, lineno: int) -> tuple[str, bool]:
    """``(site, ours)`` for a source position, named as :class:`SyncCounter` names its sites."""
    roots = _our_roots()
    path = os.path.abspath(filename)
    return f"{_display(path, roots)}:{lineno}", path.startswith(roots)


def count_syncs(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Dict[str, int]:
    """Run ``fn(*args, **kwargs)`` and return ``{"path:line": count}`` of its stalling ops, every
    site (filter with :func:`ours`)."""
    with SyncCounter() as counter:
        fn(*args, **kwargs)
    return dict(counter.counts)


def ours(counts: Dict[str, int]) -> Dict[str, int]:
    """The entries of a :func:`count_syncs` result that are sites inside this package."""
    return {site: n for site, n in counts.items() if site.startswith("sp_plugins/")}


@contextlib.contextmanager
def counting() -> Iterator[SyncCounter]:
    """``with counting() as c:`` (the same as ``with SyncCounter() as c:``)."""
    with SyncCounter() as counter:
        yield counter
