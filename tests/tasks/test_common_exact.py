"""The fitting tasks' shared pieces (sp_plugins.tasks.common), exactly: which ``--device`` names resolve
to what and which are refused with which line (CUDA / MPS availability set by the test), the stage lines
and their timing, the counting bar, the output folder's checks, the all-or-none result files, the loss
curve's figure, the running mean, and the step timer on the CPU and with CUDA events (stand-ins that keep
CUDA's rules). The mutants each test kills are listed in ``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import errno
import os
import sys

import pytest
import torch

from sp_plugins.tasks import common
from sp_plugins.tasks.common import StagedOutputs, StepTimer, counting_bar, prepare_output_dir, resolve_device, smooth, stage

CHOICES = "auto, cpu, cuda, cuda:N or mps"


def cuda(monkeypatch, available: bool, count: int = 0) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: available)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: count)


def refusal(name) -> str:
    with pytest.raises(ValueError) as e:
        resolve_device(name)
    return str(e.value)


def test_auto_is_cuda_only_where_it_is_available(monkeypatch):
    """``auto``, None (and the default) give ``cuda`` with CUDA, else the CPU."""
    cuda(monkeypatch, False)
    assert resolve_device("auto") == resolve_device(None) == resolve_device() == torch.device("cpu")
    cuda(monkeypatch, True, 1)
    assert resolve_device("auto") == resolve_device(None) == resolve_device() == torch.device("cuda")
    assert resolve_device("".join(["au", "to"])) == torch.device("cuda")  # a parsed flag: equal, not the same object
    assert resolve_device("cpu") == torch.device("cpu") and resolve_device(torch.device("cpu")) == torch.device("cpu")


def test_cuda_names_are_checked_against_the_machine(monkeypatch):
    """With 3 CUDA devices ``cuda``, ``cuda:0`` to ``cuda:2`` resolve and ``cuda:3`` is refused naming
    cuda:0 to cuda:2 (3, not 2: ``count >> 1`` is ``count - 1`` for 2); without CUDA any cuda name is refused."""
    cuda(monkeypatch, True, 3)
    assert [resolve_device(n) for n in ("cuda", "cuda:0", "cuda:2")] == [torch.device("cuda"), torch.device("cuda", 0), torch.device("cuda", 2)]
    assert refusal("cuda:3") == "--device cuda:3: this machine has 3 CUDA device(s), cuda:0 to cuda:2"
    assert refusal("cuda:4") == "--device cuda:4: this machine has 3 CUDA device(s), cuda:0 to cuda:2"
    cuda(monkeypatch, False)
    for name in ("cuda", "cuda:0"):
        assert refusal(name) == f"--device {name}: CUDA is not available on this machine; use --device cpu (or auto)"
    assert resolve_device("cpu") == torch.device("cpu")


def test_mps_only_where_apple_s_backend_is_there(monkeypatch):
    """``mps`` resolves where ``torch.backends.mps`` says it is available, else one line."""
    cuda(monkeypatch, False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert refusal("mps") == "--device mps: Apple's MPS is not available on this machine; use --device cpu (or auto)"
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    assert resolve_device("mps") == torch.device("mps")


def test_other_devices_and_non_devices_are_refused_in_one_line(monkeypatch):
    """A device type torch knows but the tasks do not run on (meta, xpu) names the choices; a name that
    is no device at all (torch raises RuntimeError) or a value torch refuses with ValueError (an index
    past 64 bits) says so with the flag."""
    cuda(monkeypatch, False)
    for name in ("meta", "xpu"):
        assert refusal(name) == f"--device {name}: the fitting tasks run on {CHOICES}"
    for name in ("gpu", "cuda:x", ""):
        assert refusal(name) == f"--device {name}: not a device; use {CHOICES}"
    assert refusal(2**70) == f"--device {2**70}: not a device; use {CHOICES}"


class Clock:
    """``time.perf_counter`` reading the given times in turn."""

    def __init__(self, *times):
        self.times = list(times)

    def __call__(self):
        return self.times.pop(0)


def test_stage_names_the_step_and_its_seconds(monkeypatch, capsys):
    """Enabled by default: ``prefix: what ...`` before, ``prefix: what: done in 2.3 s`` after (4.34 - 2.0
    seconds, one decimal; the end at least twice the start, where ``%`` is not ``-``); nothing when disabled."""
    monkeypatch.setattr(common.time, "perf_counter", Clock(2.0, 4.34, 5.0, 6.0))
    with stage("meshing"):
        print("inside", file=sys.stderr)
    with stage("quiet", enabled=False):
        pass
    assert capsys.readouterr().err == "sp-fit: meshing ...\ninside\nsp-fit: meshing: done in 2.3 s\n"


def test_the_counting_bar_counts_the_points_and_clears_itself(capsys):
    """The wrapped function returns ``fn``'s output; the bar (shown by default) counts every point it was
    called on, with SI-scaled numbers, and leaves no line behind when closed."""
    f, bar = counting_bar(lambda x: x * 2, 10, "pts")
    assert torch.equal(f(torch.ones(3)), torch.full((3,), 2.0))
    f(torch.zeros(4, 3))
    assert bar.n == 7
    bar.close()
    err = capsys.readouterr().err
    assert err.startswith("\rpts:   0%|          | 0.00/10.0 [") and err.endswith("\r") and "\n" not in err, repr(err)
    g, quiet = counting_bar(lambda x: x, 10, "pts", enabled=False)
    g(torch.ones(3))
    quiet.close()
    assert capsys.readouterr().err == ""


def test_the_output_folder_is_refused_only_when_it_holds_results_and_no_overwrite(tmp_path):
    """A new nested folder is created (parents too); one holding none of the outputs is used as is; one
    holding some is refused naming them unless ``overwrite``."""
    nested = tmp_path / "a" / "b"
    assert prepare_output_dir(nested, ["mesh.ply", "metrics.json"], False) == nested and nested.is_dir()
    assert prepare_output_dir(nested, ["mesh.ply", "metrics.json"], False) == nested  # exists, holds none
    (nested / "metrics.json").write_text("{}")
    with pytest.raises(ValueError) as e:
        prepare_output_dir(nested, ["mesh.ply", "metrics.json"], False)
    assert str(e.value) == (f"--out {nested}: already holds results (metrics.json); pass --overwrite to replace them "
                            "or choose another --out")
    assert prepare_output_dir(str(nested), ["mesh.ply", "metrics.json"], True) == nested


def test_a_folder_that_cannot_be_made_is_one_line(tmp_path):
    """``--out`` a dangling link: nothing is there to refuse, the probe passes (its parent is writable),
    and making the folder fails (File exists): one ``ValueError`` naming ``--out``."""
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "gone" / "away")
    with pytest.raises(ValueError) as e:
        prepare_output_dir(link, ["mesh.ply"], False)
    assert str(e.value) == f"--out {link}: cannot write (File exists); choose another output folder"


def test_staged_results_land_together_and_removed_ones_go(tmp_path):
    """On success every staged file is renamed into place (the temporary names gone) and each removed
    name is deleted, also one that was not there."""
    (tmp_path / "old.png").write_text("stale")
    (tmp_path / "a.txt").write_text("before")
    with StagedOutputs(tmp_path) as staged:
        staged.path("a.txt").write_text("A")
        staged.path("b.txt").write_text("B")
        staged.remove("old.png")
        staged.remove("never.png")
        assert (tmp_path / "a.txt").read_text() == "before" and (tmp_path / "old.png").exists()
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt"]
    assert (tmp_path / "a.txt").read_text() == "A" and (tmp_path / "b.txt").read_text() == "B"


def test_an_error_in_the_block_leaves_the_earlier_results_and_is_not_swallowed(tmp_path):
    """A non-OS error in the block propagates as it is (not turned into a write failure, not
    suppressed), the staged files are deleted, earlier results and files to remove stay; a staged name
    whose temporary path cannot be unlinked (a folder) does not replace the error."""
    (tmp_path / "a.txt").write_text("before")
    with pytest.raises(RuntimeError, match="^boom$"):
        with StagedOutputs(tmp_path) as staged:
            staged.path("a.txt").write_text("A")
            staged.path("dir").mkdir()
            staged.remove("a.txt")
            raise RuntimeError("boom")
    assert sorted(os.listdir(tmp_path)) == [f".tmp-{os.getpid()}-dir", "a.txt"]
    assert (tmp_path / "a.txt").read_text() == "before"


def test_an_os_error_names_the_file_it_hit_else_the_last_staged(tmp_path):
    """An ``OSError`` whose file is one of the staged temporary paths names that result; one without a
    file name names the last staged (the file being written); nothing is left. The failing file is staged
    after one whose name sorts after it (``c.png`` before ``b.json``)."""
    out = str(tmp_path)
    with pytest.raises(ValueError) as e:
        with StagedOutputs(tmp_path) as staged:
            for name in ("c.png", "b.json", "a.ply"):
                staged.path(name).write_text(name)
            raise OSError(errno.ENOSPC, "No space left on device", str(staged.path("b.json")))
    assert str(e.value) == (f"--out {out}: cannot write (b.json: No space left on device); the disk is full (or a quota "
                            "or file-size limit is reached): free space or write elsewhere; nothing was written (results "
                            "already there are unchanged)")
    with pytest.raises(ValueError) as e:
        with StagedOutputs(tmp_path, "--save") as staged:
            staged.path("a.ply").write_text("a")
            staged.path("b.json").write_text("b")
            raise OSError(errno.EACCES, "Permission denied")
    assert str(e.value).startswith(f"--save {out}: cannot write (b.json: Permission denied); the folder is read-only")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("fault", ["never written", "a folder there"])
def test_a_rename_that_would_fail_leaves_every_earlier_result(tmp_path, fault):
    """All or none at the commit too: a staged file that was never written, or a result name that is a
    folder (``--overwrite`` keeps it), is found before any rename, so the earlier run's ``a.ply`` stays and
    the line names the file and says nothing was written (before the fix ``a.ply`` was already replaced
    when ``b.json``'s rename failed: a line saying "unchanged" over a changed folder)."""
    (tmp_path / "a.ply").write_text("before")
    if fault == "a folder there":
        (tmp_path / "b.json").mkdir()
    with pytest.raises(ValueError) as e:
        with StagedOutputs(tmp_path) as staged:
            staged.path("a.ply").write_text("after")
            b = staged.path("b.json")
            if fault == "a folder there":
                b.write_text("b")
    reason = "No such file or directory" if fault == "never written" else "a folder has this name"
    assert str(e.value) == (f"--out {tmp_path}: cannot write (b.json: {reason}); choose another output folder; nothing "
                            "was written (results already there are unchanged)")
    assert (tmp_path / "a.ply").read_text() == "before"
    assert sorted(os.listdir(tmp_path)) == (["a.ply"] if fault == "never written" else ["a.ply", "b.json"])


def test_the_loss_curve_figure(tmp_path, monkeypatch):
    """6 x 4 inches at 110 dpi (a 660 x 440 PNG); each curve a line of width 1 against its index unless
    ``xs``; each mark a grey dashed line of width 0.8 with its label at the top (y 1.0 in axes units,
    size 8); log scale unless ``log=False``; the title only when given; the legend at size 8; the grid
    at alpha 0.3."""
    from PIL import Image
    import matplotlib.pyplot as plt

    figures = []
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig: (figures.append(fig), close(fig)))
    path = common.plot_curves({"sp": [4.0, 2.0, 1.0], "plain": [3.0, 3.0]}, tmp_path / "c.png", marks=[(1.0, "end")], title="T")
    assert path == tmp_path / "c.png" and Image.open(path).size == (660, 440)
    common.plot_curves(curves={"sp": [1.0, 2.0]}, path=tmp_path / "d.png", xs=[5.0, 7.0], log=False, ylabel="psnr")
    with pytest.raises(TypeError):  # the options are keyword-only
        common.plot_curves({"sp": [1.0]}, tmp_path / "e.png", [5.0])
    (fig, fig2) = figures
    (ax,), (ax2,) = fig.axes, fig2.axes
    assert tuple(fig.get_size_inches()) == (6.0, 4.0)
    sp, plain, mark = ax.lines
    assert (sp.get_label(), list(sp.get_xdata()), list(sp.get_ydata()), sp.get_linewidth()) == ("sp", [0, 1, 2], [4.0, 2.0, 1.0], 1)
    assert (plain.get_label(), list(plain.get_xdata()), plain.get_linewidth()) == ("plain", [0, 1], 1)
    assert (list(mark.get_xdata()), mark.get_linestyle(), mark.get_linewidth(), mark.get_color()) == ([1.0, 1.0], "--", 0.8, "gray")
    (text,) = ax.texts
    assert (text.get_text(), text.get_position(), text.get_fontsize(), text.get_va()) == (" end", (1.0, 1.0), 8.0, "top")
    assert (ax.get_yscale(), ax.get_xlabel(), ax.get_ylabel(), ax.get_title()) == ("log", "step", "loss", "T")
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["sp", "plain"] and ax.get_legend().get_texts()[0].get_fontsize() == 8
    assert ax.xaxis.get_gridlines()[0].get_alpha() == 0.3 and ax.xaxis.get_gridlines()[0].get_visible()
    (line,) = ax2.lines
    assert list(line.get_xdata()) == [5.0, 7.0] and ax2.get_yscale() == "linear" and ax2.get_title() == ""
    assert ax2.get_ylabel() == "psnr" and len(ax2.texts) == 0


def test_smooth_is_the_running_mean_over_the_window():
    """Window 3 over six values: the mean of the last (up to) 3, exactly; a window longer than the
    values: the mean so far; window 1 or 0 and no values: the values as they are (even where a cumulative
    sum would round: 1e16 then 1); one value: its float."""
    assert smooth([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], 3) == [1.0, 1.5, 2.0, 3.0, 4.0, 5.0]
    assert smooth([2.0, 4.0, 9.0], 5) == [2.0, 3.0, 5.0]
    assert smooth([4.0, 8.0, 2.0, 6.0], 2) == [4.0, 6.0, 5.0, 4.0]
    for window in (1, 0):
        assert smooth([1e16, 1.0, 3.0], window) == [1e16, 1.0, 3.0]
    assert smooth([], 3) == [] and smooth([], 1) == []
    one = smooth([5], 3)
    assert one == [5.0] and type(one[0]) is float
    assert all(type(v) is float for v in smooth([1, 2, 3], 2))


def test_the_step_timer_on_the_cpu(monkeypatch):
    """On the CPU (or no device) each step's time is ``perf_counter`` at its end minus at its start; the times are
    readable, replaceable (a resume) and summed by ``total``. Apple's ``mps`` (and any device but CUDA) times the
    same way."""
    monkeypatch.setattr(common.time, "perf_counter", Clock(1.0, 2.25, 3.0, 6.125, 7.0, 14.5))
    for timer, device in ((StepTimer("cpu"), torch.device("cpu")), (StepTimer(), None), (StepTimer("mps"), torch.device("mps"))):
        assert timer.device == device
        with timer:
            pass
        assert timer.times == [{"cpu": 1.25, None: 3.125, "mps": 7.5}[device and device.type]]
    timer = StepTimer("cpu")
    timer.times = (2.0, 0.5)
    assert timer.times == [2.0, 0.5] and timer.total == 2.5 and type(timer.total) is float


class Event:
    """A CUDA event's rules: ``elapsed_time`` (milliseconds) only between two events made with
    ``enable_timing=True`` that were recorded and synchronized."""

    clock = [0.0]

    def __init__(self, enable_timing=False):
        self.timing, self.t, self.synced = enable_timing, None, False

    def record(self, stream=None):
        self.t = self.clock[0]

    def synchronize(self):
        self.synced = True

    def elapsed_time(self, end):
        assert self.timing and end.timing, "Both events must be created with argument enable_timing=True"
        assert end.synced and self.t is not None and end.t is not None
        return end.t - self.t


def test_the_step_timer_reads_cuda_events_in_seconds(monkeypatch):
    """On CUDA a step records a start and an end event (both with timing) on the device's stream; the
    times are the events' milliseconds / 1000, read when asked, once."""
    monkeypatch.setattr(torch.cuda, "Event", Event)
    monkeypatch.setattr(torch.cuda, "current_stream", lambda device=None: device)
    timer = StepTimer("cuda:0")
    for start, end in ((0.0, 250.0), (300.0, 425.0)):
        Event.clock[0] = start
        timer.__enter__()
        Event.clock[0] = end
        timer.__exit__(None, None, None)
    assert timer.times == [0.25, 0.125] and timer.times == [0.25, 0.125] and timer.total == 0.375
