"""The host-neutral training callbacks that drive SP (sp_plugins.adapter.callbacks), exactly: the step and
run length SP is moved to (fresh, resumed, a run that says no start step as sdfstudio's), when, the schedule
refusal's bounds and line, the alpha grid's learning rate. Where each host keeps the run length is the host's
(``sp_run_length``, tested with each host's model); no host import here. The mutants each test kills are listed in ``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from sp_plugins.adapter import callbacks as cb
from sp_plugins.adapter.errors import InputError
from sp_plugins.core import SPConfig, SPRun


def attributes(optimizers=None):
    """A host's callback attributes, as far as the callbacks read them: the optimizers."""
    return SimpleNamespace(optimizers=optimizers)


class Made:
    """The host's ``make(where, func)``: records what was asked, returns the pair."""

    def __init__(self):
        self.asked = []

    def __call__(self, where, func):
        self.asked.append(where)
        return where, func


def preconditioner(**config):
    return SPConfig(alpha0=0.5, boundary="none", schedule="linear", end=0.5, **config).setup(dim=3)


def hosted(sp, reach=None):
    """``sp`` as a host model wraps it (``SPModelBase.populate_modules``)."""
    return SPRun.over(sp, reach=reach, sets_mode=False, alpha_grid_optimizer=False)


def test_a_run_length_is_ints_or_none():
    """What a host reads comes back as ints (a float from a config too), None where it says nothing (not 0)."""
    assert cb.run_length(300.0, 7) == (300, 7) and type(cb.run_length(300.0).total) is int
    assert cb.run_length(None) == (None, None) and cb.run_length(40, 0) == (40, 0)


@pytest.mark.parametrize("end, fits", [(100, True), (101, False), (1.0, True), (0.5, True), (2, True)])
def test_the_schedule_refusal_bounds_and_its_line_name_the_flags_typed(end, fits):
    """A schedule may end at the last step of a run of 100 (``end`` 100 or 1.0), not after it (101). The
    refusal names ``--pipeline.model.sp.end`` and the host's run-length flag. A relative alpha (a
    fraction of the diagonal) fits the same."""
    for relative in (True, False):
        config = SPConfig(alpha0=0.02, schedule="step", end=end, relative_to_diagonal=relative)
        problem = cb.schedule_problem(config, 100, "--trainer.max-num-iterations")
        if fits:
            assert problem is None, problem
        else:
            assert problem.startswith("--pipeline.model.sp.end 101 does not fit --trainer.max-num-iterations 100 (end=101")
            assert problem.endswith("give --pipeline.model.sp.end as a fraction of training in (0, 1] or a step "
                                    "<= --trainer.max-num-iterations")
    if not fits:
        assert "does not fit --max-num-iterations 100" in cb.schedule_problem(SPConfig(schedule="step", end=end), 100, "--max-num-iterations")


def test_a_fresh_nerfstudio_run_starts_sp_at_step_0_of_its_length_and_steps_before_every_iteration():
    """Registration moves SP to (start, total) at once; the first callback runs *before* each iteration and
    moves it to the trainer's step, with this run's length (also over a checkpoint of a run of another length,
    loaded after registration); the second runs after it."""
    sp, make = preconditioner(), Made()
    sp.set_step(33, 1000)  # whatever it held
    callback, _ = cb.sp_callbacks(hosted(sp), cb.run_length(200, 0), attributes(), make, "--max-num-iterations")
    assert make.asked == ["before", "after"] and (int(sp.step), int(sp.total_steps)) == (0, 200)
    assert sp.alpha == pytest.approx(0.5)
    where, step_to = callback
    step_to(50)  # linear to 0 at step 100 (end 0.5 of 200)
    assert (int(sp.step), int(sp.total_steps)) == (50, 200) and sp.alpha == pytest.approx(0.25)
    step_to(100)
    assert sp.alpha == 0.0
    sp.set_step(100, 999)  # a checkpoint loaded after registration (nerfstudio loads it after the callbacks) restores its run's length
    step_to(101)
    assert (int(sp.step), int(sp.total_steps)) == (101, 200)  # this run's length again


def test_a_resumed_run_continues_at_its_start_step():
    """``trainer._start_step`` (the checkpoint's step + 1) is where SP is moved at registration, so the
    first resumed step has the alpha it would have had."""
    sp = preconditioner()
    cb.sp_callbacks(hosted(sp), cb.run_length(200, 60), attributes(), Made(), "--max-num-iterations")
    assert int(sp.step) == 60 and sp.alpha == pytest.approx(0.5 * (1 - 60 / 100))


def test_sdfstudio_s_attributes_keep_the_step_the_checkpoint_loaded():
    """sdfstudio's attributes carry no start step: SP stays at the step its state holds (0 on a fresh
    run, the checkpoint's after a load), with the run's length set."""
    sp = preconditioner()
    sp.set_step(42, 1000)  # as a loaded checkpoint left it
    cb.sp_callbacks(hosted(sp), cb.run_length(200, None), attributes(), Made(), "--trainer.max-num-iterations")
    assert (int(sp.step), int(sp.total_steps)) == (42, 200)


def test_without_a_run_length_sp_keeps_its_saved_total():
    """No ``max_num_iterations`` (a loader, not a trainer): no check, no move; the callback keeps the
    total in SP's state."""
    sp = preconditioner()
    sp.set_step(5, 400)
    callback, _ = cb.sp_callbacks(hosted(sp), cb.run_length(None), attributes(), Made(), "--max-num-iterations")
    assert (int(sp.step), int(sp.total_steps)) == (5, 400)
    callback[1](10)
    assert (int(sp.step), int(sp.total_steps)) == (10, 400)


def test_the_hosts_reach_check_runs_once_after_the_first_training_step_with_alpha_above_0():
    """The *after* callback runs the host's reach check exactly once: after the first training iteration whose
    alpha is above 0 (not before it, not in evaluation mode, not again); the *before* callback leaves the mode to
    the host (its viewer renders in evaluation mode between steps)."""
    sp, checked = SPConfig(alpha0=0.5, boundary="none", schedule="linear", end=100).setup(dim=3), []
    sp.set_step(0, 200)
    before, after = cb.sp_callbacks(hosted(sp, reach=checked.append), cb.run_length(200, 100), attributes(), Made(),
                                    "--max-num-iterations")
    for step in (100, 101):  # alpha is 0 from step 100 (a resumed run past the end): nothing to check
        before[1](step)
        after[1](step)
    assert checked == []
    sp.eval()
    before[1](0)
    assert not sp.training  # the mode is the host's
    after[1](0)
    assert checked == []  # evaluation: nothing moves, nothing to check
    sp.train()
    for step in (1, 2, 3):
        before[1](step)
        after[1](step)
    assert checked == [1] and sp.training


def test_a_schedule_that_does_not_fit_is_refused_before_sp_moves():
    sp = SPConfig(schedule="step", end=300, boundary="none").setup(dim=3)
    with pytest.raises(InputError, match=r"^--pipeline\.model\.sp\.end 300 does not fit --trainer\.max-num-iterations 200 "):
        cb.sp_callbacks(hosted(sp), cb.run_length(200, 0), attributes(), Made(), "--trainer.max-num-iterations")
    assert int(sp.total_steps) == -1  # not moved


def test_the_alpha_grid_group_gets_the_configured_lr_and_no_other_group_does():
    """Every param group of the alpha grid's optimizer, ``lr`` and ``initial_lr`` (a resumed scheduler
    reads the latter), from ``--pipeline.model.sp.alpha-grid-lr``; other groups untouched; nothing done
    without a grid or without that group."""
    sp = SPConfig(boundary="none", alpha_grid=True, alpha_grid_lr=3e-3).setup(dim=3)
    grid_opt = torch.optim.Adam([{"params": [torch.zeros(2, requires_grad=True)]}, {"params": [torch.zeros(3, requires_grad=True)]}], lr=1.0)
    for g in grid_opt.param_groups:
        g["initial_lr"] = 1.0
    field_opt = torch.optim.Adam([torch.zeros(2, requires_grad=True)], lr=0.1)
    optimizers = SimpleNamespace(optimizers={cb.ALPHA_GRID_GROUP: grid_opt, "fields": field_opt})
    cb.sp_callbacks(hosted(sp), cb.run_length(10, 0), attributes(optimizers), Made(), "--max-num-iterations")
    assert [(g["lr"], g["initial_lr"]) for g in grid_opt.param_groups] == [(3e-3, 3e-3)] * 2
    assert field_opt.param_groups[0]["lr"] == 0.1 and "initial_lr" not in field_opt.param_groups[0]

    no_grid = SPConfig(boundary="none", alpha_grid_lr=3e-3).setup(dim=3)
    other = torch.optim.Adam([torch.zeros(2, requires_grad=True)], lr=1.0)
    cb.sync_alpha_grid_lr(no_grid, SimpleNamespace(optimizers=SimpleNamespace(optimizers={cb.ALPHA_GRID_GROUP: other})))
    assert other.param_groups[0]["lr"] == 1.0  # SP without a grid: its group (if any) is not SP's
    cb.sync_alpha_grid_lr(sp, SimpleNamespace(optimizers=None))  # nothing to do, no error
    cb.sync_alpha_grid_lr(sp, SimpleNamespace(optimizers=SimpleNamespace(optimizers={"fields": field_opt})))
    assert field_opt.param_groups[0]["lr"] == 0.1


def test_the_alpha_grid_optimizer_entry_is_adam_at_the_configured_lr_without_a_scheduler():
    """The alpha grid's optimizer entry: Adam at the config's ``alpha_grid_lr`` with ``eps`` 1e-15, and no
    scheduler."""
    made = cb.alpha_grid_optimizer(SPConfig(alpha_grid_lr=2e-3), lambda **kw: kw)
    assert made == {"optimizer": {"lr": 2e-3, "eps": 1e-15}, "scheduler": None}


@pytest.mark.parametrize("start, first", [(None, 0), (0, 0), (25, 25)])
def test_a_models_own_schedule_is_applied_at_once_at_the_start_step_then_before_every_iteration(start, first):
    """FreeNeRF's mask and Neuralangelo's coarse-to-fine: ``at(step, total)`` at registration with the start
    step (0 when the attributes do not say), then before each iteration."""
    calls, make = [], Made()
    where, update = cb.model_schedule_callback(lambda step, total: calls.append((step, total)),
                                               cb.run_length(80, start), make)
    assert where == "before" and make.asked == ["before"] and calls == [(first, 80)]
    update(31)
    assert calls == [(first, 80), (31, 80)]


def test_the_schedule_refusal_names_the_host_s_sp_flags():
    """The refusal names SP's flags as the host registers them (``Flags.sp``), not one host's spelling."""
    config = SPConfig(schedule="step", end=300)
    line = cb.schedule_problem(config, 200, "--steps", "--model.sp")
    assert line.startswith("--model.sp.end 300 does not fit --steps 200 (") and "give --model.sp.end as a fraction" in line
    assert "--pipeline.model.sp" in cb.schedule_problem(config, 200, "--steps")  # the default: both hosts' spelling
