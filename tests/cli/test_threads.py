import psutil
import pytest
import torch

from sp_plugins.cli import threads


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


class FakeProcess:
    def __init__(self, percent):
        self.percent = percent

    def cpu_percent(self, interval=None):
        return self.percent


@pytest.mark.parametrize("total, own, free", [(0.0, 0.0, 4), (24.0, 0.0, 3), (50.0, 0.0, 2), (75.0, 0.0, 1),
                                               (100.0, 0.0, 1), (50.0, 200.0, 4), (75.0, 100.0, 2)])
def test_free_cores_leaves_out_the_cores_other_processes_keep_busy(monkeypatch, total, own, free):
    """total: percent of all 4 cores; own: this process's percent of one core (spinning OpenMP workers)."""
    monkeypatch.setattr(threads, "usable_cores", lambda: 4)
    monkeypatch.setattr(psutil, "cpu_count", lambda *a, **k: 4)
    monkeypatch.setattr(psutil, "cpu_percent", lambda interval=None, **k: total)
    monkeypatch.setattr(psutil, "Process", lambda *a: FakeProcess(own))
    assert threads.free_cores(window=0.0) == free


def test_pick_threads_uses_the_free_cores_and_says_so(monkeypatch, restore_threads):
    monkeypatch.setattr(threads, "usable_cores", lambda: 2)
    monkeypatch.setattr(threads, "free_cores", lambda window=0.3: 1)
    torch.set_num_threads(2)
    said = []
    assert threads.pick_threads(None, log=said.append, prog="sp-demo") == 1
    assert torch.get_num_threads() == 1
    assert len(said) == 1 and "1 of 2 cores are busy" in said[0] and "--threads" in said[0]


def test_pick_threads_obeys_an_explicit_count_without_measuring(monkeypatch, restore_threads):
    monkeypatch.setattr(threads, "free_cores", lambda window=0.3: pytest.fail("measured despite --threads"))
    assert threads.pick_threads(2, log=pytest.fail) == 2 and torch.get_num_threads() == 2
    with pytest.raises(ValueError, match="--threads must be at least 1"):
        threads.pick_threads(0)


def test_pick_threads_never_exceeds_torchs_default(monkeypatch, restore_threads):
    """On an idle machine with hyperthreads, free cores outnumber torch's one-per-physical-core default."""
    monkeypatch.setattr(threads, "usable_cores", lambda: 8)
    monkeypatch.setattr(threads, "free_cores", lambda window=0.3: 8)
    torch.set_num_threads(4)
    assert threads.pick_threads(None, log=pytest.fail) == 4 and torch.get_num_threads() == 4
