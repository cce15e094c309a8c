"""sp_plugins.sync_count: every kind of stalling op is counted at the line that caused it, torch's
CPU-by-design reads are not, and a device filter leaves out ops a GPU run keeps on the CPU."""

import sys

import numpy as np
import torch

from sp_plugins.sync_count import SyncCounter, count_syncs, ours, site_of


def _here(offset: int) -> str:
    frame = sys._getframe(1)
    return f"{site_of(frame.f_code.co_filename, frame.f_lineno + offset)[0]}"


def test_each_kind_is_counted_at_its_line():
    x = torch.randn(64)
    expected = {}
    with SyncCounter() as counter:
        expected[_here(1)] = "aten._local_scalar_dense"
        x.sum().item()
        expected[_here(1)] = "aten._local_scalar_dense"
        bool((x > 0).any())
        expected[_here(1)] = "aten.index"
        x[x > 0]
        expected[_here(1)] = "aten._unique2"
        torch.unique(x)
        expected[_here(1)] = "aten.nonzero"
        x.nonzero()
        expected[_here(1)] = "aten.masked_select"
        torch.masked_select(x, x > 0)
        expected[_here(1)] = "Tensor.tolist"
        x.tolist()
        expected[_here(1)] = "Tensor.numpy"
        np.asarray(x)
        expected[_here(1)] = "aten._local_scalar_dense"
        f"{x.sum():.3f}"
        x[torch.arange(3)]  # an integer index: no sync
        x * 2
    assert {site: list(ops) for site, ops in counter.ops.items()} == {site: [op] for site, op in expected.items()}
    assert x.tolist() and not hasattr(torch.Tensor.tolist, "__wrapped__")  # the wrappers are gone afterwards


def test_an_optimizers_step_counter_is_not_ours_and_sites_inside_the_package_are():
    p = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([p])
    p.grad = torch.ones(3)
    assert count_syncs(opt.step) == {}  # torch/optim reads CPU step counters: CPU tensors on a GPU run too

    from sp_plugins.tasks.common import smooth

    counts = count_syncs(smooth, [1.0, 2.0, 3.0], 2)  # reads its running means back with float(): host code
    assert ours(counts) and all(site.startswith("sp_plugins/tasks/common.py:") for site in ours(counts))
    assert sum(ours(counts).values()) == 3


def test_a_device_filter_counts_only_ops_on_that_device():
    x = torch.randn(8)
    with SyncCounter(devices={"cuda"}) as counter:
        x.sum().item()
        x.tolist()
    assert not counter.counts
