"""No sp-fit training step of ours waits for the GPU: counted on the CPU as the operators that would
stall a CUDA stream (``sp_plugins.sync_count``), per call site, over a few steps of each task."""

import numpy as np
import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.sync_count import SyncCounter
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.image import ImageFitConfig
from sp_plugins.tasks.pointcloud import PointCloudSDFConfig
from sp_plugins.tasks.sdf import SDFFitConfig

GRID_2D = EncodingConfig(levels=4, log2_table_size=10, base_resolution=4, max_resolution=32)


@pytest.fixture(autouse=True)
def gpu_code_paths():
    """Boundaries take their GPU branch (the dense fold): the CPU's sparse reflect reads the count of
    escaped coordinates back on purpose, a path a CUDA run never takes."""
    from sp_plugins.core.boundary import dense_fold

    with dense_fold():
        yield


def image(size=32):
    rng = np.random.default_rng(0)
    return rng.random((size, size, 3)).astype(np.float32)


def _trainers(blob_points, blob_mesh, tiny_grid):
    yield "pointcloud", PointCloudSDFConfig(steps=20, surface_batch=64, space_batch=64, encoding=tiny_grid, hidden=(16,)).setup(blob_points)
    yield "pointcloud, alpha grid", PointCloudSDFConfig(
        steps=20, surface_batch=64, space_batch=64, encoding=tiny_grid, hidden=(16,),
        sp=SPConfig(alpha0=0.03, end=0.5, alpha_grid=True, alpha_grid_resolution=4)).setup(blob_points)
    yield "sdf", SDFFitConfig(steps=20, batch=128, pool=400, encoding=tiny_grid, hidden=(16,)).setup(blob_mesh)
    yield "image", ImageFitConfig(steps=20, batch=256, encoding=GRID_2D, hidden=(16,)).setup(image())
    # phase 2 from step 3: importance sampling and level masking read the frozen map
    yield "image, alpha map, phase 2", ImageFitConfig(
        steps=20, batch=256, encoding=GRID_2D, hidden=(16,), adaptive_alpha=True, importance_sampling=True,
        level_masking=True, level_mask_min_levels=2.0, sp=SPConfig(alpha0=0.02, schedule="step", end=0.15)).setup(image())


def test_no_training_step_of_ours_syncs(blob_points, blob_mesh, tiny_grid):
    found = {}
    for name, trainer in _trainers(blob_points, blob_mesh, tiny_grid):
        for _ in range(4):  # warm-up, and the image's switch to phase 2 (once per run, not per step)
            trainer.step()
        with SyncCounter() as counter:
            for _ in range(3):
                trainer.step()
        if counter.ours():
            found[name] = counter.report(only_ours=True)
        assert trainer.step_index == 7
    assert not found, "host-device syncs in a training step:\n" + "\n".join(f"{k}:\n{v}" for k, v in found.items())


def test_a_fit_reads_its_numbers_once_per_logging_interval(blob_points, tiny_grid):
    from sp_plugins.tasks.trainer import LOG_EVERY

    trainer = PointCloudSDFConfig(steps=2 * LOG_EVERY + 10, surface_batch=64, space_batch=64, encoding=tiny_grid,
                                  hidden=(16,)).setup(blob_points)
    with SyncCounter() as counter:
        trainer.fit(progress=True)
    assert sum(counter.ours().values()) == 3, counter.report()  # after steps 25 and 50, and at the end
    assert len(trainer.history["loss"]) == 2 * LOG_EVERY + 10 and len(trainer.timer.times) == 2 * LOG_EVERY + 10


def test_a_non_finite_loss_stops_at_the_next_read_naming_its_step(blob_mesh, tiny_grid):
    trainer = SDFFitConfig(steps=20, batch=128, pool=400, encoding=tiny_grid, hidden=(16,)).setup(blob_mesh)
    for _ in range(3):
        trainer.step()
    with torch.no_grad():
        trainer.field.mlp[-1].bias.fill_(float("nan"))
    records = [trainer.step() for _ in range(3)]  # steps 3..5 queue on; nothing read yet
    with pytest.raises(FloatingPointError, match=r"^step 3: the loss became nan; the fit diverged: lower --lr"):
        records[-1]["loss"]
    assert trainer.step_index == 6


def test_step_timer_uses_cuda_events_read_only_with_the_times(monkeypatch):
    """On CUDA a step's kernels are only queued when it returns: the timer records events and reads
    them when asked (no synchronize inside a step)."""
    from sp_plugins.tasks.common import StepTimer

    log = []

    class FakeEvent:
        def __init__(self, enable_timing):
            assert enable_timing
            self.t = None

        def record(self, stream):
            self.t = len(log)
            log.append("record")

        def synchronize(self):
            log.append("sync")

        def elapsed_time(self, end):
            return 1000.0 * (end.t - self.t)  # milliseconds

    monkeypatch.setattr(torch.cuda, "Event", FakeEvent)
    monkeypatch.setattr(torch.cuda, "current_stream", lambda device=None: None)
    timer = StepTimer("cuda")
    for _ in range(3):
        with timer:
            pass
    assert log == ["record"] * 6  # nothing waited for yet
    assert timer.times == [1.0, 1.0, 1.0] and log.count("sync") == 3
    assert timer.total == 3.0 and log.count("sync") == 3  # read once
