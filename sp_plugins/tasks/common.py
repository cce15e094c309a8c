"""Pieces shared by the fitting tasks: devices, output folders, loss curves, step timing,
progress lines for the slow steps after training. The trainers' base classes are in
:mod:`sp_plugins.tasks.trainer`."""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Literal, Mapping, Optional, Sequence, Union

import torch

from sp_plugins.adapter.checks import check_writable_dir, existing_outputs
from sp_plugins.adapter.errors import write_failure


DEVICE_CHOICES = "auto, cpu, cuda, cuda:N or mps"


def resolve_device(name: Union[str, torch.device, None] = "auto") -> torch.device:
    """The torch device for ``--device NAME``: ``auto`` (or None) is CUDA when available, else the
    CPU. An unknown name or a device this machine does not have is a ``ValueError`` naming the flag."""
    if name is None or str(name) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise ValueError(f"--device {name}: not a device; use {DEVICE_CHOICES}") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {name}: CUDA is not available on this machine; use --device cpu (or auto)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                             f"cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    elif device.type == "mps":
        if not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
            raise ValueError(f"--device {name}: Apple's MPS is not available on this machine; use --device cpu (or auto)")
    elif device.type != "cpu":
        raise ValueError(f"--device {name}: the fitting tasks run on {DEVICE_CHOICES}")
    return device


@contextlib.contextmanager
def stage(what: str, enabled: bool = True, prefix: str = "sp-fit") -> Iterator[None]:
    """Say what a slow step is doing, and how long it took (stderr, one line each)."""
    start = time.perf_counter()
    if enabled:
        print(f"{prefix}: {what} ...", file=sys.stderr, flush=True)
    yield
    if enabled:
        print(f"{prefix}: {what}: done in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)


def counting_bar(fn: Callable, total: int, desc: str, enabled: bool = True):
    """``fn`` with a tqdm bar that counts the points it has been called on, and the bar (close it)."""
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc=desc, unit="pt", unit_scale=True, disable=not enabled, leave=False)

    def wrapped(x):
        out = fn(x)
        bar.update(len(x))
        return out

    return wrapped, bar


def prepare_output_dir(out: Union[str, Path], outputs: Iterable[str], overwrite: bool) -> Path:
    """Create ``out`` or check that it holds none of ``outputs`` (unless ``overwrite``), and that
    files can be written there (a read-only folder or a full disk is named before any training)."""
    out = Path(out)
    existing = existing_outputs(out, outputs, "--out")
    if existing and not overwrite:
        raise ValueError(
            f"--out {out}: already holds results ({', '.join(existing)}); pass --overwrite to replace "
            "them or choose another --out"
        )
    check_writable_dir(out, "--out")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(write_failure(exc, f"--out {out}")) from None
    return out


class StagedOutputs:
    """A command's result files, all or none: each is written to a temporary name in ``out``
    (same suffix, so writers pick the format), and :meth:`commit` renames them into place together.
    A write that fails (full disk, read-only folder) removes the temporary files and raises one
    ``ValueError`` naming ``--out``: results of an earlier run stay as they were.

        with StagedOutputs(out) as staged:
            save_mesh(mesh, staged.path("mesh.ply"))
            staged.remove("alpha_map.png")   # an earlier run's file that would mislead
    """

    def __init__(self, out: Union[str, Path], flag: str = "--out") -> None:
        import os

        self.out, self.flag = Path(out), flag
        self._tag = f".tmp-{os.getpid()}-"
        self._staged: dict = {}
        self._removed: list = []

    def path(self, name: str) -> Path:
        tmp = self.out / f"{self._tag}{name}"
        self._staged[name] = tmp
        return tmp

    def remove(self, name: str) -> None:
        """Delete ``out/name`` at commit (not before: a failed run leaves it)."""
        self._removed.append(name)

    def __enter__(self) -> "StagedOutputs":
        return self

    def __exit__(self, kind, exc, tb) -> "Literal[False]":  # never swallows; quoted: no False literal to mutate
        import errno
        import os

        if exc is None:
            try:
                for name, tmp in self._staged.items():  # before any rename: one that would fail leaves none made
                    tmp.stat()  # a staged file never written: FileNotFoundError naming it
                    if (self.out / name).is_dir():  # a folder of that name (kept by --overwrite) cannot be replaced
                        raise IsADirectoryError(errno.EISDIR, "a folder has this name", str(tmp))
                for name, tmp in self._staged.items():
                    os.replace(tmp, self.out / name)
                for name in self._removed:
                    (self.out / name).unlink(missing_ok=True)
                return False
            except OSError as err:
                exc = err
        for tmp in self._staged.values():
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
        if isinstance(exc, OSError):
            failed = next((name for name, tmp in self._staged.items() if exc.filename and Path(exc.filename).name == tmp.name),
                          next(reversed(self._staged), None))  # else the file being written: the last one staged
            raise ValueError(write_failure(exc, f"{self.flag} {self.out}", failed)
                             + "; nothing was written (results already there are unchanged)") from None
        return False


def plot_curves(
    curves: Mapping[str, Sequence[float]],
    path: Union[str, Path],
    *,
    xs: Optional[Sequence[float]] = None,
    xlabel: str = "step",
    ylabel: str = "loss",
    title: str = "",
    log: bool = True,
    marks: Sequence[tuple[float, str]] = (),
) -> Path:
    """One line per curve (x = index unless ``xs``), vertical lines at ``marks``; a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, ys in curves.items():
        ax.plot(xs if xs is not None else range(len(ys)), ys, label=name, lw=1)
    for x, label in marks:
        ax.axvline(x, color="gray", ls="--", lw=0.8)
        ax.text(x, 1.0, f" {label}", transform=ax.get_xaxis_transform(), va="top", fontsize=8, color="gray")
    if log:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    path = Path(path)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def smooth(values: Sequence[float], window: int) -> list[float]:
    """Running mean over ``window`` steps (for readable loss curves)."""
    if window <= 1 or len(values) == 0:
        return list(values)
    t = torch.tensor(values, dtype=torch.float64)
    c = torch.cat([torch.zeros(1, dtype=torch.float64), t.cumsum(0)])
    out = []
    for i in range(len(values)):
        lo = max(0, i - window + 1)
        out.append(float((c[i + 1] - c[lo]) / (i + 1 - lo)))
    return out


class StepTimer:
    """Time of each step, for per-step cost ratios.

    On the CPU a step's work is done when it returns: ``perf_counter``. On CUDA it has only been
    queued, so each step records a pair of CUDA events instead and ``times`` reads them later (the
    stream's time from reaching the step's start to finishing its last kernel, the backward pass
    included): no host-device sync per step, only when the times are read."""

    def __init__(self, device: Union[str, torch.device, None] = None) -> None:
        self.device = torch.device(device) if device is not None else None
        self._cuda = self.device is not None and self.device.type == "cuda"
        self._times: list[float] = []
        self._pending: list = []  # (start, end) CUDA events not read yet
        self._start: Any = None

    def __enter__(self) -> "StepTimer":
        if self._cuda:
            self._start = torch.cuda.Event(enable_timing=True)
            self._start.record(torch.cuda.current_stream(self.device))
        else:
            self._start = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        assert self._start is not None
        if self._cuda:
            end = torch.cuda.Event(enable_timing=True)
            end.record(torch.cuda.current_stream(self.device))
            self._pending.append((self._start, end))
        else:
            self._times.append(time.perf_counter() - self._start)
        self._start = None

    @property
    def times(self) -> list[float]:
        """Seconds per step (waits for the queued steps' events on CUDA)."""
        for start, end in self._pending:
            end.synchronize()
            self._times.append(start.elapsed_time(end) / 1000.0)
        self._pending = []
        return self._times

    @times.setter
    def times(self, values: Iterable[float]) -> None:
        self._times, self._pending = list(values), []

    @property
    def total(self) -> float:
        return float(sum(self.times))
