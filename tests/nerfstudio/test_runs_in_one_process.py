"""``sp_plugins.nerfstudio.runs.train`` trains runs one after another in one process (the benchmarks do): each
run's event file holds its own scalars only. nerfstudio keeps its event writers in a module list that its
trainer appends to and never clears, so before the fix the second run also wrote into the first run's file
and ``sp-compare`` plotted two runs' curves interleaved as one."""

from __future__ import annotations

import nerfstudio.configs.base_config  # noqa: F401  (nerfstudio's writer module imports only after its configs)
import pytest
from nerfstudio.utils import writer

from sp_plugins.nerfstudio.runs import train


def _loss_steps(run_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (file,) = sorted(run_dir.glob("events.out.tfevents.*"))
    events = EventAccumulator(str(file), size_guidance={"scalars": 0})
    events.Reload()
    return [e.step for e in events.Scalars("Train Loss")]


def test_two_runs_in_one_process_write_only_their_own_event_files(tiny_scene, tmp_path, tiny_config):
    writers_before = len(writer.EVENT_WRITERS)
    dirs = []
    for name, steps in (("neus-hashgrid", 3), ("sp-neus-hashgrid", 5)):
        config = tiny_config(name, tiny_scene, tmp_path / name, steps=steps)
        config.logging.steps_per_log = 1
        train(config)
        dirs.append(config.get_base_dir())
    assert _loss_steps(dirs[0]) == [0, 1, 2]  # not [0, 0, 1, 1, 2, 2, 3, 4]: the second run stayed out
    assert _loss_steps(dirs[1]) == [0, 1, 2, 3, 4]
    assert len(writer.EVENT_WRITERS) == writers_before


def test_a_run_that_fails_drops_its_writers_too(tiny_scene, tmp_path, tiny_config, monkeypatch):
    from nerfstudio.engine.trainer import Trainer

    def fails(self, step):
        assert len(writer.EVENT_WRITERS) > writers_before  # the run's writers exist when it fails
        raise RuntimeError("a failing step")

    writers_before = len(writer.EVENT_WRITERS)
    monkeypatch.setattr(Trainer, "train_iteration", fails)
    with pytest.raises(RuntimeError, match="a failing step"):
        train(tiny_config("sp-neus-hashgrid", tiny_scene, tmp_path, steps=2))
    assert len(writer.EVENT_WRITERS) == writers_before


def test_the_same_config_trained_twice_in_one_process_gives_the_same_weights(tiny_scene, tmp_path, tiny_config):
    """``runs.train`` seeds as ``ns-train`` does (``--machine.seed``): before, it trained from whatever state the
    process's generator was in, so two trainings of one config (the sparse-view pair) scored differently."""
    import torch

    weights = []
    for name in ("a", "b", "c"):
        config = tiny_config("sp-neus-hashgrid", tiny_scene, tmp_path / name, steps=3)
        if name == "c":
            config.machine.seed = 43
        torch.rand(7)  # the process's generator moved on between the runs, as it does in a benchmark
        trainer = train(config)
        weights.append({k: v.clone() for k, v in trainer.pipeline.model.state_dict().items() if torch.is_tensor(v) and v.is_floating_point()})
    assert weights[0].keys() == weights[1].keys() and len(weights[0]) > 10
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert sum(not torch.equal(weights[0][k], weights[2][k]) for k in weights[0]) > len(weights[0]) // 2
